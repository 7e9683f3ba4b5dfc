//! `--sweep`: other fields of each scene (channels, Gaussians kept, map resolution, iterations),
//! each scored on ChatSplat's answers, and the plot of exact match against views/s.

use crate::Args;
use model::Result;
use model::vqa::Level;
use scoring::compare::Tally;
use scoring::plot::{Chart, Series};

/// One way to make a scene's field in the sweep, scored by ChatSplat's answers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Variant {
    /// The field as configured, every Gaussian (the reference point).
    Configured,
    /// The field as `train-language` leaves it by default: compacted (compact.json), the
    /// comparison's (c).
    Compacted,
    /// Language features of this many channels per level.
    Channels(usize),
    /// The configured field with only this percentage of its Gaussians, those with the largest
    /// accumulated language gradient (no retraining).
    Kept(usize),
    /// Maps rendered at this many pixels per token (the configured: the views' resolution).
    Patch(usize),
    /// The language stage with 1/this of its iterations.
    LanguageIters(usize),
    /// Geometry trained with 1/this of its iterations, then the configured language stage.
    GeometryIters(usize),
}

pub(crate) const SWEEP: [Variant; 10] = [
    Variant::Configured,
    Variant::Compacted,
    Variant::Channels(8),
    Variant::Channels(16),
    Variant::Channels(64),
    Variant::Kept(50),
    Variant::Kept(25),
    Variant::Kept(10),
    Variant::Patch(6),
    Variant::LanguageIters(2),
];

/// Geometry iterations are swept on their own (a second geometry run per scene).
pub(crate) const GEOMETRY_SWEEP: Variant = Variant::GeometryIters(4);

impl Variant {
    pub(crate) fn name(self, a: &Args, channels: usize) -> String {
        match self {
            Variant::Configured => format!("configured ({channels} ch, all Gaussians)"),
            Variant::Compacted => "compacted (the default: compact.json)".into(),
            Variant::Channels(c) => format!("{c} channels"),
            Variant::Kept(p) => format!("{p} % of the Gaussians kept"),
            Variant::Patch(p) => format!("map at {p} px per token"),
            Variant::LanguageIters(d) => format!("language {} iterations", a.language_iters / d),
            Variant::GeometryIters(d) => format!("geometry {} iterations", a.geometry_iters / d),
        }
    }

    /// The plot series a point belongs to.
    pub(crate) fn axis(self) -> &'static str {
        match self {
            Variant::Configured | Variant::Channels(_) => "channels",
            Variant::Kept(_) | Variant::Compacted => "Gaussians kept",
            Variant::Patch(_) => "map resolution",
            Variant::LanguageIters(_) | Variant::GeometryIters(_) => "iterations",
        }
    }
}

/// A sweep point summed over the scenes.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
pub(crate) struct Point {
    pub(crate) name: String,
    pub(crate) axis: String,
    pub(crate) tally: Tally,
    pub(crate) token_seconds: scoring::compare::TokenSeconds,
    /// Language-stage seconds per iteration, summed over the scenes that trained one.
    pub(crate) train_seconds: f64,
    pub(crate) trained: usize,
    pub(crate) gaussians: usize,
    pub(crate) field_bytes: usize,
    pub(crate) scenes: usize,
}

impl Point {
    pub(crate) fn add(&mut self, o: &Point) {
        self.tally.merge(&o.tally);
        for (level, (t, n)) in &o.token_seconds {
            let e = self.token_seconds.entry(*level).or_default();
            e.0 += t;
            e.1 += n;
        }
        self.train_seconds += o.train_seconds;
        self.trained += o.trained;
        self.gaussians += o.gaussians;
        self.field_bytes += o.field_bytes;
        self.scenes += o.scenes;
    }
    pub(crate) fn rate(&self, level: Level) -> f64 {
        self.token_seconds.get(&level).map(|(t, n)| *n as f64 / t.max(1e-9)).unwrap_or(f64::NAN)
    }
    pub(crate) fn kind(&self, kind: &str) -> String {
        self.tally
            .by_kind
            .get(kind)
            .map(|(r, n)| format!("{:.1}", 100.0 * *r as f64 / (*n).max(1) as f64))
            .unwrap_or("-".into())
    }
}

/// Adds `p` to the point of its name in `points`, or appends it (the sweep's order).
pub(crate) fn add_point(points: &mut Vec<Point>, p: &Point) {
    match points.iter_mut().find(|q| q.name == p.name) {
        Some(q) => q.add(p),
        None => points.push(p.clone()),
    }
}

/// Prints the sweep's table and writes its plot: ChatSplat's exact match against views/s, one
/// series per axis through the configured field, the Pareto front, and the rendered-RGB baseline
/// (`baseline`: its views/s and exact match, when the runs timed it); `label` says which runs,
/// over `scenes` held-out scenes.
pub(crate) fn sweep_report(
    points: &[Point],
    baseline: Option<(f64, f64)>,
    (label, scenes): (&str, u64),
    out: &std::path::Path,
) -> Result<()> {
    println!("\n## Speed against error on ChatSplat's answers ({label})\n");
    println!(
        "| field | Gaussians | field MB | view | object | scene | overall | count | colors | left_of | views/s \
         | objects/s | train s/iter |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for p in points {
        let n = p.scenes.max(1);
        let lv = |l: Level| p.tally.level(l).map(|v| format!("{v:.1}")).unwrap_or_else(|| "-".into());
        let (right, asked) = p.tally.by_level.values().fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        let train = if p.trained > 0 { format!("{:.3}", p.train_seconds / p.trained as f64) } else { "-".into() };
        println!(
            "| {} | {} | {:.2} | {} | {} | {} | {:.1} ({right}/{asked}) | {} | {} | {} | {:.1} | {:.1} | {train} |",
            p.name,
            p.gaussians / n,
            p.field_bytes as f64 / n as f64 / 1e6,
            lv(Level::View),
            lv(Level::Object),
            lv(Level::Scene),
            p.tally.overall(),
            p.kind("count"),
            p.kind("colors"),
            p.kind("left_of"),
            p.rate(Level::View),
            p.rate(Level::Object),
        );
    }
    let xy = |p: &Point| (p.rate(Level::View), p.tally.overall());
    let all: Vec<(f64, f64)> = points.iter().map(xy).collect();
    let front = scoring::plot::pareto_front(&all);
    println!(
        "\nPareto front (views/s against exact match): {}",
        front.iter().map(|&i| points[i].name.as_str()).collect::<Vec<_>>().join(" -> ")
    );
    let colors = [[31, 119, 180], [214, 39, 40], [44, 160, 44], [148, 103, 189]];
    let mut series = Vec::new();
    for (k, axis) in ["channels", "Gaussians kept", "map resolution", "iterations"].into_iter().enumerate() {
        let mut pts: Vec<(f64, f64)> =
            points.iter().filter(|p| p.axis == axis || p.name.starts_with("configured")).map(xy).collect();
        pts.sort_by(|p, q| p.0.total_cmp(&q.0));
        series.push(Series { label: axis.into(), points: pts, color: colors[k] });
    }
    series.push(Series {
        label: "Pareto front".into(),
        points: front.iter().map(|&i| all[i]).collect(),
        color: [0; 3],
    });
    if let Some(b) = baseline {
        series.push(Series { label: "LLaVA-OV on rendered RGB".into(), points: vec![b], color: [120; 3] });
    }
    let chart = Chart {
        title: format!("ChatSplat answers: speed against exact match ({scenes} held-out scenes)"),
        x_label: "views per second (view tokens)".into(),
        y_label: "exact match (%)".into(),
        log_x: true,
        series,
    };
    let png = out.join("sweep.png");
    chart.write_png(&png, 900, 600)?;
    println!("plot -> {}", png.display());
    Ok(())
}
