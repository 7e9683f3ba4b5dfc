//! A small dependency-free chart writer for benchmark plots such as "error against speed": an RGB8 raster with
//! axes, round-number ticks (log10 on x when asked), a title, axis labels, one polyline with markers per series
//! and a legend, all lettered with a built-in 5x7 bitmap font; PNG output goes through the `png` crate.

use std::path::Path;

/// One data series: `points` are `(x, y)` pairs in data units, drawn in the given order as markers joined by
/// lines. Points with a non-finite coordinate (or `x <= 0` on a log x axis) are skipped.
pub struct Series {
    /// Legend text (ASCII; lower case is drawn as upper case, characters without a glyph as `?`).
    pub label: String,
    pub points: Vec<(f64, f64)>,
    /// Line and marker colour, RGB8.
    pub color: [u8; 3],
}

/// A line chart: `series` share one pair of axes whose ranges cover all their drawable points (padded by 5%;
/// empty or constant data get a default range). `log_x` puts x on a log10 scale with decade ticks.
pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub log_x: bool,
    pub series: Vec<Series>,
}

/// Tick positions (data units) with their labels.
type Ticks = Vec<(f64, String)>;

const BLACK: [u8; 3] = [0, 0, 0];
const GRID: [u8; 3] = [225, 225, 225];
const RIGHT: i64 = 16;
const BOTTOM: i64 = 36;

/// Plot rectangle in pixels (`x0..x1` left to right, `y0..y1` top to bottom) and the data ranges it shows;
/// the x range is in log10 units when `log_x`.
struct Frame {
    x0: f64,
    y0: f64,
    x1: f64,
    y1: f64,
    xr: (f64, f64),
    yr: (f64, f64),
    log_x: bool,
}

impl Frame {
    fn px(&self, x: f64) -> f64 {
        let t = if self.log_x { x.log10() } else { x };
        self.x0 + (t - self.xr.0) / (self.xr.1 - self.xr.0) * (self.x1 - self.x0)
    }

    fn py(&self, y: f64) -> f64 {
        self.y1 - (y - self.yr.0) / (self.yr.1 - self.yr.0) * (self.y1 - self.y0)
    }

    /// Pixel of a data point, clamped well inside i64 so that line drawing stays bounded.
    fn pixel(&self, (x, y): (f64, f64)) -> (i64, i64) {
        let c = |v: f64| if v.is_nan() { 0 } else { v.round().clamp(-1e5, 1e5) as i64 };
        (c(self.px(x)), c(self.py(y)))
    }
}

impl Chart {
    /// Renders the chart as `width * height` RGB8 pixels, row-major from the top-left (`width * height * 3`
    /// bytes). Never panics on degenerate data or tiny sizes; parts that do not fit are clipped.
    pub fn render(&self, width: u32, height: u32) -> Vec<u8> {
        let mut cv = Canvas { w: width as i64, h: height as i64, px: vec![255; width as usize * height as usize * 3] };
        let (fr, xt, yt) = self.layout(width, height);
        let (x0, y0, x1, y1) = (fr.x0 as i64, fr.y0 as i64, fr.x1 as i64, fr.y1 as i64);
        for (v, label) in &xt {
            let x = fr.px(*v).round() as i64;
            cv.line((x, y0), (x, y1), 1, GRID);
            cv.line((x, y1), (x, y1 + 4), 1, BLACK);
            cv.text(x - text_w(label, 1) / 2, y1 + 7, label, 1, false, BLACK);
        }
        for (v, label) in &yt {
            let y = fr.py(*v).round() as i64;
            cv.line((x0, y), (x1, y), 1, GRID);
            cv.line((x0 - 4, y), (x0, y), 1, BLACK);
            cv.text(x0 - 7 - text_w(label, 1), y - 3, label, 1, false, BLACK);
        }
        for (a, b) in [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))] {
            cv.line(a, b, 1, BLACK);
        }
        cv.text((width as i64 - text_w(&self.title, 2)) / 2, 9, &self.title, 2, false, BLACK);
        cv.text((x0 + x1 - text_w(&self.x_label, 1)) / 2, y1 + 22, &self.x_label, 1, false, BLACK);
        cv.text(6, (y0 + y1 + text_w(&self.y_label, 1)) / 2, &self.y_label, 1, true, BLACK);
        let pts: Vec<Vec<(i64, i64)>> =
            self.series.iter().map(|s| self.drawable(s).map(|p| fr.pixel(p)).collect()).collect();
        for (s, p) in self.series.iter().zip(&pts) {
            p.windows(2).for_each(|w| cv.line(w[0], w[1], 2, s.color));
        }
        for (i, (s, p)) in self.series.iter().zip(&pts).enumerate() {
            p.iter().for_each(|&q| cv.marker(q, i, s.color));
        }
        self.legend(&mut cv, &fr, &pts);
        cv.px
    }

    /// Renders the chart and writes it as an 8-bit RGB PNG, atomically; errors name `path`.
    pub fn write_png(&self, path: &Path, width: u32, height: u32) -> model::Result<()> {
        model::images::write_rgb8(path, width, height, &self.render(width, height))
    }

    fn drawable<'a>(&self, s: &'a Series) -> impl Iterator<Item = (f64, f64)> + 'a {
        let log_x = self.log_x;
        s.points.iter().copied().filter(move |(x, y)| x.is_finite() && y.is_finite() && (!log_x || *x > 0.0))
    }

    /// The plot frame and the labelled x and y ticks (in data units) for an image of this size.
    fn layout(&self, width: u32, height: u32) -> (Frame, Ticks, Ticks) {
        let all = || self.series.iter().flat_map(|s| self.drawable(s));
        let xr = padded_range(all().map(|(x, _)| if self.log_x { x.log10() } else { x }), self.log_x);
        let yr = padded_range(all().map(|(_, y)| y), false);
        let top = if self.title.is_empty() { 12.0 } else { 32.0 };
        let target = |len: f64, per: f64| (len / per).clamp(2.0, 8.0);
        let yt = nice_ticks(yr.0, yr.1, target(height as f64 - top - BOTTOM as f64, 40.0));
        let left = 27 + yt.iter().map(|(_, l)| text_w(l, 1)).max().unwrap_or(0);
        let xt = if self.log_x {
            log_ticks(xr.0, xr.1)
        } else {
            nice_ticks(xr.0, xr.1, target(width as f64 - left as f64 - RIGHT as f64, 70.0))
        };
        let (x0, y0) = (left as f64, top);
        let (x1, y1) = ((width as f64 - RIGHT as f64).max(x0 + 1.0), (height as f64 - BOTTOM as f64).max(y0 + 1.0));
        (Frame { x0, y0, x1, y1, xr, yr, log_x: self.log_x }, xt, yt)
    }

    /// Legend box in the plot corner that covers the fewest data points.
    fn legend(&self, cv: &mut Canvas, fr: &Frame, pts: &[Vec<(i64, i64)>]) {
        if self.series.is_empty() {
            return;
        }
        let w = 38 + self.series.iter().map(|s| text_w(&s.label, 1)).max().unwrap_or(0);
        let h = 12 * self.series.len() as i64 + 5;
        let (l, t, r, b) = (fr.x0 as i64 + 6, fr.y0 as i64 + 6, fr.x1 as i64 - 6 - w, fr.y1 as i64 - 6 - h);
        let inside = |(x, y): (i64, i64), p: &(i64, i64)| {
            (x - 5..=x + w + 5).contains(&p.0) && (y - 5..=y + h + 5).contains(&p.1)
        };
        let covered = |&c: &(i64, i64)| pts.iter().flatten().filter(|p| inside(c, p)).count();
        let (x, y) = [(r, t), (l, t), (r, b), (l, b)].into_iter().min_by_key(covered).unwrap();
        cv.rect(x, y, x + w, y + h, BLACK);
        cv.rect(x + 1, y + 1, x + w - 1, y + h - 1, [255; 3]);
        for (i, s) in self.series.iter().enumerate() {
            let row = y + 6 + 12 * i as i64;
            cv.line((x + 5, row + 3), (x + 25, row + 3), 2, s.color);
            cv.marker((x + 15, row + 3), i, s.color);
            cv.text(x + 32, row, &s.label, 1, false, BLACK);
        }
    }
}

/// Min and max of `vals` with 5% margins; empty data give (0, 1), a single value is padded (by half a decade in
/// log space, else by 10% of its magnitude or 1).
fn padded_range(vals: impl Iterator<Item = f64>, log: bool) -> (f64, f64) {
    let (lo, hi) = vals.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if lo > hi {
        return (0.0, 1.0);
    }
    let (lo, hi) = if hi - lo > 1e-9 * lo.abs().max(hi.abs()) {
        (lo, hi)
    } else {
        let pad = if log {
            0.5
        } else if lo == 0.0 {
            1.0
        } else {
            0.1 * lo.abs()
        };
        (lo - pad, hi + pad)
    };
    (lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo))
}

/// Labelled ticks at multiples of a 1, 2 or 5 x 10^k step giving about `target` intervals over [lo, hi] (at least
/// two ticks when the range is valid).
fn nice_ticks(lo: f64, hi: f64, target: f64) -> Ticks {
    let raw = (hi - lo) / target;
    if !(raw.is_finite() && raw > 0.0) {
        return Vec::new();
    }
    let mag = 10f64.powf(raw.log10().floor());
    for step in [10.0, 5.0, 2.0, 1.0, 0.5, 0.2, 0.1].map(|m| m * mag).into_iter().filter(|s| *s <= 1.5 * raw) {
        let (a, b) = ((lo / step).ceil(), (hi / step).floor());
        if b - a >= 1.0 && b - a < 100.0 {
            return (a as i64..=b as i64).map(|k| k as f64 * step).map(|v| (v, fmt_num(v, step))).collect();
        }
    }
    Vec::new()
}

/// Labelled ticks for a log10 axis over [lo, hi] (log units), in data units: decades (thinned to at most ~9) when
/// there are three or more, else 1-2-5 x 10^k ticks, else linear ones.
fn log_ticks(lo: f64, hi: f64) -> Ticks {
    let (a, b) = (lo.ceil(), hi.floor());
    if (b - a).is_nan() || b - a >= 400.0 {
        return Vec::new();
    }
    let every = ((b - a) / 8.0).ceil().max(1.0) as i64;
    let label = |v: f64| (v, fmt_num(v, 10f64.powf((v.log10() + 1e-9).floor())));
    let decades: Vec<_> =
        (a as i64..=b as i64).filter(|k| k.rem_euclid(every) == 0).map(|k| label(10f64.powi(k as i32))).collect();
    if decades.len() >= 3 {
        return decades;
    }
    let fine: Vec<_> = (a as i64 - 1..=b as i64)
        .flat_map(|k| [1.0, 2.0, 5.0].map(|m| m * 10f64.powi(k as i32)))
        .filter(|v| (lo..=hi).contains(&v.log10()))
        .map(label)
        .collect();
    if fine.len() >= 2 { fine } else { nice_ticks(10f64.powf(lo), 10f64.powf(hi), 4.0) }
}

/// Formats a tick value with as many decimals as `step` needs (scientific for very large or small values).
fn fmt_num(v: f64, step: f64) -> String {
    let v = if v.abs() < step * 1e-6 { 0.0 } else { v };
    let e = (step.log10() + 1e-9).floor();
    if v.abs() >= 1e6 || step < 1e-4 {
        let digits = if v == 0.0 { 0.0 } else { (v.abs().log10().floor() - e).clamp(0.0, 6.0) };
        format!("{:.*e}", digits as usize, v)
    } else {
        format!("{:.*}", (-e).max(0.0) as usize, v)
    }
}

/// Width in pixels of `s` in the 5x7 font (6 px advance) at `scale`.
fn text_w(s: &str, scale: i64) -> i64 {
    (s.chars().count() as i64 * 6 - 1).max(0) * scale
}

/// 5x7 glyphs, hand-drawn: byte r (most significant first) is row r from the top, bit 4 the leftmost column.
#[rustfmt::skip]
const FONT: &[(char, u64)] = &[
    ('0', 0x0E_11_13_15_19_11_0E), ('1', 0x04_0C_04_04_04_04_0E),
    ('2', 0x0E_11_01_02_04_08_1F), ('3', 0x1F_02_04_02_01_11_0E),
    ('4', 0x02_06_0A_12_1F_02_02), ('5', 0x1F_10_1E_01_01_11_0E),
    ('6', 0x06_08_10_1E_11_11_0E), ('7', 0x1F_01_02_04_08_08_08),
    ('8', 0x0E_11_11_0E_11_11_0E), ('9', 0x0E_11_11_0F_01_02_0C),
    ('A', 0x0E_11_11_1F_11_11_11), ('B', 0x1E_11_11_1E_11_11_1E),
    ('C', 0x0E_11_10_10_10_11_0E), ('D', 0x1C_12_11_11_11_12_1C),
    ('E', 0x1F_10_10_1E_10_10_1F), ('F', 0x1F_10_10_1E_10_10_10),
    ('G', 0x0E_11_10_17_11_11_0F), ('H', 0x11_11_11_1F_11_11_11),
    ('I', 0x0E_04_04_04_04_04_0E), ('J', 0x07_02_02_02_02_12_0C),
    ('K', 0x11_12_14_18_14_12_11), ('L', 0x10_10_10_10_10_10_1F),
    ('M', 0x11_1B_15_15_11_11_11), ('N', 0x11_11_19_15_13_11_11),
    ('O', 0x0E_11_11_11_11_11_0E), ('P', 0x1E_11_11_1E_10_10_10),
    ('Q', 0x0E_11_11_11_15_12_0D), ('R', 0x1E_11_11_1E_14_12_11),
    ('S', 0x0F_10_10_0E_01_01_1E), ('T', 0x1F_04_04_04_04_04_04),
    ('U', 0x11_11_11_11_11_11_0E), ('V', 0x11_11_11_11_11_0A_04),
    ('W', 0x11_11_11_15_15_15_0A), ('X', 0x11_11_0A_04_0A_11_11),
    ('Y', 0x11_11_0A_04_04_04_04), ('Z', 0x1F_01_02_04_08_10_1F),
    ('.', 0x00_00_00_00_00_0C_0C), (',', 0x00_00_00_00_0C_04_08),
    ('-', 0x00_00_00_1F_00_00_00), ('+', 0x00_04_04_1F_04_04_00),
    ('/', 0x01_01_02_04_08_10_10), ('(', 0x02_04_08_08_08_04_02),
    (')', 0x08_04_02_02_02_04_08), ('%', 0x18_19_02_04_08_13_03),
    (':', 0x00_0C_0C_00_0C_0C_00), ('=', 0x00_00_1F_00_1F_00_00),
    ('_', 0x00_00_00_00_00_00_1F), (' ', 0x00_00_00_00_00_00_00),
    ('[', 0x0E_08_08_08_08_08_0E), (']', 0x0E_02_02_02_02_02_0E),
    ('^', 0x04_0A_11_00_00_00_00), ('?', 0x0E_11_01_02_04_00_04),
];

/// The rows of `c`'s glyph (lower case uses upper case; characters without a glyph get `?`).
fn glyph(c: char) -> [u8; 7] {
    let find = |c: char| FONT.iter().find(|(k, _)| *k == c).map(|(_, g)| *g);
    let g = find(c.to_ascii_uppercase()).or_else(|| find('?')).unwrap_or(0);
    std::array::from_fn(|r| (g >> (8 * (6 - r))) as u8)
}

/// RGB8 pixels with clipped drawing primitives.
struct Canvas {
    w: i64,
    h: i64,
    px: Vec<u8>,
}

impl Canvas {
    fn set(&mut self, x: i64, y: i64, c: [u8; 3]) {
        if (0..self.w).contains(&x) && (0..self.h).contains(&y) {
            let i = ((y * self.w + x) * 3) as usize;
            self.px[i..i + 3].copy_from_slice(&c);
        }
    }

    /// Filled rectangle, corners inclusive (clipped to the canvas).
    fn rect(&mut self, x0: i64, y0: i64, x1: i64, y1: i64, c: [u8; 3]) {
        for y in y0.max(0)..=y1.min(self.h - 1) {
            for x in x0.max(0)..=x1.min(self.w - 1) {
                self.set(x, y, c);
            }
        }
    }

    /// Bresenham line with a `thick` x `thick` square brush.
    fn line(&mut self, (mut x, mut y): (i64, i64), (x1, y1): (i64, i64), thick: i64, c: [u8; 3]) {
        let (dx, dy) = ((x1 - x).abs(), -(y1 - y).abs());
        let (sx, sy) = ((x1 - x).signum(), (y1 - y).signum());
        let mut err = dx + dy;
        loop {
            self.rect(x - (thick - 1) / 2, y - (thick - 1) / 2, x + thick / 2, y + thick / 2, c);
            if x == x1 && y == y1 {
                return;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }

    /// Marker for series `index`: filled 7x7 squares for even indices, filled circles of radius 4 for odd ones.
    fn marker(&mut self, (x, y): (i64, i64), index: usize, c: [u8; 3]) {
        let square = index.is_multiple_of(2);
        let r: i64 = if square { 3 } else { 4 };
        for dy in -r..=r {
            for dx in -r..=r {
                if square || dx * dx + dy * dy <= r * r {
                    self.set(x + dx, y + dy, c);
                }
            }
        }
    }

    /// Text with its top-left glyph corner at (x, y); `vertical` rotates it 90 degrees anticlockwise so that it
    /// reads upwards starting at (x, y).
    fn text(&mut self, x: i64, y: i64, s: &str, scale: i64, vertical: bool, c: [u8; 3]) {
        for (i, ch) in s.chars().enumerate() {
            for (row, bits) in glyph(ch).iter().enumerate() {
                for col in 0..5 {
                    if bits & (0x10 >> col) == 0 {
                        continue;
                    }
                    let (u, v) = ((i as i64 * 6 + col) * scale, row as i64 * scale);
                    let (bx, by) = if vertical { (x + v, y - u - scale + 1) } else { (x + u, y + v) };
                    self.rect(bx, by, bx + scale - 1, by + scale - 1, c);
                }
            }
        }
    }
}

/// The Pareto front of `points` when larger is better on both axes (e.g. views/s and accuracy):
/// the indices of the points no other point beats on one axis without losing on the other, in
/// increasing x. Points with a non-finite coordinate are never on it.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let ok = |p: &(f64, f64)| p.0.is_finite() && p.1.is_finite();
    let dominated = |i: usize| {
        let a = points[i];
        points.iter().any(|b| ok(b) && b.0 >= a.0 && b.1 >= a.1 && (b.0 > a.0 || b.1 > a.1))
    };
    let mut front: Vec<usize> = (0..points.len()).filter(|&i| ok(&points[i]) && !dominated(i)).collect();
    front.sort_by(|&i, &j| points[i].0.total_cmp(&points[j].0));
    front
}

#[cfg(test)]
mod tests {
    use super::*;

    const RED: [u8; 3] = [200, 30, 40];

    fn chart(points: Vec<(f64, f64)>, log_x: bool) -> Chart {
        let series = vec![Series { label: "Ours (1.5 ms)".into(), points, color: RED }];
        Chart { title: "Error vs speed".into(), x_label: "FPS".into(), y_label: "PSNR dB".into(), log_x, series }
    }

    fn pixel(img: &[u8], width: u32, (x, y): (i64, i64)) -> [u8; 3] {
        let i = (y as usize * width as usize + x as usize) * 3;
        [img[i], img[i + 1], img[i + 2]]
    }

    #[test]
    fn pareto_front_keeps_the_points_nothing_beats_on_both_axes() {
        let p = [(1.0, 90.0), (2.0, 85.0), (1.5, 80.0), (4.0, 70.0), (3.0, 70.0), (f64::NAN, 99.0), (4.0, 60.0)];
        assert_eq!(pareto_front(&p), vec![0, 1, 3]);
        assert_eq!(pareto_front(&[(1.0, 1.0), (1.0, 1.0)]), vec![0, 1], "ties dominate neither");
        assert!(pareto_front(&[]).is_empty());
    }

    #[test]
    fn markers_sit_at_mapped_positions() {
        let c = chart(vec![(1.0, 1.0), (2.0, 4.0), (3.0, 9.0)], false);
        let (w, h) = (320, 240);
        let img = c.render(w, h);
        assert_eq!(img.len(), (w * h * 3) as usize);
        assert_eq!(pixel(&img, w, (0, 0)), [255; 3]);
        let (fr, xt, yt) = c.layout(w, h);
        assert!(xt.len() >= 2 && yt.len() >= 2);
        let p: Vec<_> = c.series[0].points.iter().map(|&q| fr.pixel(q)).collect();
        for &(x, y) in &p {
            assert!(x > fr.x0 as i64 && x < fr.x1 as i64 && y > fr.y0 as i64 && y < fr.y1 as i64);
            assert_eq!(pixel(&img, w, (x, y)), RED);
        }
        assert!(p[0].0 < p[1].0 && p[1].0 < p[2].0, "x grows to the right");
        assert!(p[0].1 > p[1].1 && p[1].1 > p[2].1, "y grows upwards");
        // 5% padding: the extreme points sit 1/22 of the plot width inside the frame.
        let inset = (fr.x1 - fr.x0) / 22.0;
        assert!((p[0].0 as f64 - fr.x0 - inset).abs() <= 1.0 && (fr.x1 - p[2].0 as f64 - inset).abs() <= 1.0);
    }

    #[test]
    fn log_x_puts_decades_equally_apart() {
        let c = chart(vec![(10.0, 1.0), (100.0, 2.0), (1000.0, 3.0)], true);
        let (fr, xt, _) = c.layout(400, 300);
        let (a, b, d) = (fr.px(10.0), fr.px(100.0), fr.px(1000.0));
        assert!(b - a > 50.0 && ((b - a) - (d - b)).abs() < 1e-6, "{a} {b} {d}");
        assert_eq!(xt.iter().map(|(_, l)| l.as_str()).collect::<Vec<_>>(), ["10", "100", "1000"]);
        let img = c.render(400, 300);
        assert_eq!(pixel(&img, 400, fr.pixel((100.0, 2.0))), RED);
        let lin = chart(c.series[0].points.clone(), false).layout(400, 300).0;
        assert!(lin.px(100.0) - lin.px(10.0) < 0.2 * (lin.px(1000.0) - lin.px(10.0)));
    }

    #[test]
    fn degenerate_inputs_do_not_panic() {
        let nan = f64::NAN;
        let cases = [
            chart(vec![], false),
            chart(vec![(nan, 1.0), (2.0, f64::INFINITY), (nan, nan)], false),
            chart(vec![(5.0, 5.0), (5.0, 5.0)], false),
            chart(vec![(0.0, 0.0), (-1.0, 2.0)], true),
            chart(vec![(1e300, -1e300), (-1e300, 1e300)], false),
            Chart {
                title: String::new(),
                x_label: String::new(),
                y_label: String::new(),
                log_x: false,
                series: vec![],
            },
        ];
        for c in &cases {
            for (w, h) in [(0, 0), (1, 1), (7, 3), (64, 48), (320, 240)] {
                assert_eq!(c.render(w, h).len(), (w * h * 3) as usize);
            }
        }
        // A single (repeated) point is padded into the middle of the frame and drawn there.
        let (fr, _, _) = cases[2].layout(320, 240);
        let (x, y) = fr.pixel((5.0, 5.0));
        assert!((x as f64 - (fr.x0 + fr.x1) / 2.0).abs() <= 1.0 && (y as f64 - (fr.y0 + fr.y1) / 2.0).abs() <= 1.0);
        assert_eq!(pixel(&cases[2].render(320, 240), 320, (x, y)), RED);
        // A NaN point between two good ones is skipped; the others are still drawn.
        let c = chart(vec![(1.0, 1.0), (nan, 3.0), (2.0, 2.0)], false);
        let (fr, _, _) = c.layout(200, 150);
        assert_eq!(pixel(&c.render(200, 150), 200, fr.pixel((2.0, 2.0))), RED);
    }

    #[test]
    fn ticks_are_round_and_labelled() {
        let t = nice_ticks(0.0, 1.0, 5.0);
        assert_eq!(t.iter().map(|(_, l)| l.as_str()).collect::<Vec<_>>(), ["0.0", "0.2", "0.4", "0.6", "0.8", "1.0"]);
        let t = nice_ticks(-3.0, 247.0, 5.0);
        assert_eq!(t.first().unwrap().1, "0");
        assert_eq!(t.last().unwrap().1, "200");
        assert_eq!(log_ticks(-2.2, 0.1).iter().map(|(_, l)| l.as_str()).collect::<Vec<_>>(), ["0.01", "0.1", "1"]);
        assert!(log_ticks(0.1, 0.6).len() >= 2, "sub-decade log ranges still get ticks");
        assert_eq!(fmt_num(2.5e7, 5e6), "2.5e7");
        let (lo, hi) = padded_range([3.0, 3.0].into_iter(), false);
        assert!((lo - 2.67).abs() < 1e-12 && (hi - 3.33).abs() < 1e-12, "{lo} {hi}");
        assert_eq!(padded_range([f64::NAN; 0].into_iter(), true), (0.0, 1.0));
    }

    #[test]
    fn font_covers_required_characters_and_text_is_drawn() {
        let unknown = glyph('\u{7f}');
        assert_eq!(unknown, glyph('?'));
        for c in "0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz.,-+/()%:=_".chars() {
            assert_ne!(glyph(c), unknown, "no glyph for {c:?}");
            assert_ne!(glyph(c), [0; 7], "empty glyph for {c:?}");
        }
        let mut cv = Canvas { w: 40, h: 40, px: vec![255; 40 * 40 * 3] };
        cv.text(2, 30, "I", 1, true, BLACK);
        // Vertical "I" (rows 0x0E, 0x04 x5, 0x0E): its stem runs along y = 30 - 2 from x = 2 + 1 to 2 + 5.
        assert!((3..=7).all(|x| cv.px[((28 * 40 + x) * 3) as usize] == 0));
        assert_eq!(cv.px[(29 * 40 + 4) * 3], 255);
    }

    #[test]
    fn write_png_round_trips_and_reports_bad_paths() {
        let dir = std::env::temp_dir().join(format!("chatsplat_plot_test_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("chart.png");
        let c = chart(vec![(1.0, 3.0), (10.0, 2.0), (100.0, 1.5)], true);
        c.write_png(&path, 300, 200).unwrap();
        let mut reader = png::Decoder::new(std::fs::File::open(&path).unwrap()).read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height, info.color_type), (300, 200, png::ColorType::Rgb));
        assert!(buf[..info.buffer_size()] == c.render(300, 200)[..]);
        let names: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, ["chart.png"], "no temporary file left behind");
        // a path under a regular file cannot be written
        let bad = dir.join("chart.png").join("chart.png");
        let e = c.write_png(&bad, 10, 10).unwrap_err().to_string();
        assert!(e.contains(&dir.join("chart.png").display().to_string()), "{e}");
        assert!(!bad.exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
