//! What a run adds up over its scenes, its bench.json, and the printed comparison.

use crate::sweep::{Point, add_point, sweep_report};
use eval::harness::TokenFidelity;
use model::Result;
use model::find::FindTally;
use model::vqa::Level;
use scoring::compare::{FindKinds, Source, Tally};
use std::collections::BTreeMap;

/// What a run adds up over its scenes; `--merge` adds the bench.json of several runs.
#[derive(Default)]
pub(crate) struct Totals {
    pub(crate) tallies: BTreeMap<Source, Tally>,
    /// Seconds spent making tokens and how many, per path and level.
    pub(crate) seconds: BTreeMap<(Source, Level), (f64, usize)>,
    pub(crate) fid_rgb: TokenFidelity,
    pub(crate) fid_cs: TokenFidelity,
    pub(crate) points: Vec<Point>,
    /// Held-out seeds, ranges `[first, end)`.
    pub(crate) seeds: Vec<[u64; 2]>,
    /// ChatSplat's find phrases by kind, and the seconds they took.
    pub(crate) find: FindKinds,
    pub(crate) find_seconds: f64,
}

/// The parts of a bench.json that `--merge` adds (older files lack `token_seconds`).
#[derive(serde::Deserialize)]
pub(crate) struct BenchJson {
    #[serde(default)]
    pub(crate) seeds: Option<[u64; 2]>,
    #[serde(default)]
    pub(crate) seed_ranges: Vec<[u64; 2]>,
    #[serde(default)]
    pub(crate) tallies: BTreeMap<Source, Tally>,
    /// `None` in files written before the runs stored it.
    #[serde(default)]
    pub(crate) token_seconds: Option<Vec<(Source, Level, f64, usize)>>,
    /// Absent in `--find-only` runs.
    #[serde(default)]
    pub(crate) fidelity_rendered_rgb: TokenFidelity,
    #[serde(default)]
    pub(crate) fidelity_chatsplat: TokenFidelity,
    #[serde(default)]
    pub(crate) sweep: Vec<Point>,
    /// Absent in files written before find phrases were scored.
    #[serde(default)]
    pub(crate) find: FindKinds,
    #[serde(default)]
    pub(crate) find_seconds: f64,
}

impl Totals {
    pub(crate) fn add(&mut self, b: &BenchJson) {
        for (s, t) in &b.tallies {
            self.tallies.entry(*s).or_default().merge(t);
        }
        for &(s, l, t, n) in b.token_seconds.iter().flatten() {
            let e = self.seconds.entry((s, l)).or_default();
            e.0 += t;
            e.1 += n;
        }
        self.fid_rgb.add_mean(b.fidelity_rendered_rgb);
        self.fid_cs.add_mean(b.fidelity_chatsplat);
        for p in &b.sweep {
            add_point(&mut self.points, p);
        }
        self.seeds.extend(b.seeds.iter().chain(&b.seed_ranges));
        add_find(&mut self.find, &mut self.find_seconds, &b.find, b.find_seconds);
    }

    pub(crate) fn scenes(&self) -> u64 {
        self.seeds.iter().map(|[a, b]| b - a).sum()
    }

    /// "5 held-out seeds: 30000-30002, 30003, 30004".
    pub(crate) fn label(&self) -> String {
        let ranges: Vec<String> = self
            .seeds
            .iter()
            .map(|&[a, b]| if b == a + 1 { a.to_string() } else { format!("{a}-{}", b - 1) })
            .collect();
        format!("{} held-out seeds: {}", self.scenes(), ranges.join(", "))
    }
}

/// Prints the comparison (and the sweep, when there is one) and writes bench.json (`settings`
/// first) and sweep.png into `out`.
pub(crate) fn report(t: &Totals, what: &str, settings: serde_json::Value, out: &std::path::Path) -> Result<()> {
    let empty = Tally::default();
    let tally = |s: Source| t.tallies.get(&s).unwrap_or(&empty);
    println!("\n## ChatSplat vs the VLM on images ({}, {what})\n", t.label());
    if t.tallies.is_empty() {
        // --find-only: no answers, no token figures
        find_report(t);
        return write_bench(t, settings, serde_json::json!({}), out);
    }
    println!("| path | view | object | scene | overall | questions |\n|---|---|---|---|---|---|");
    // the paths run (`--chatsplat-only`: ChatSplat's alone)
    let sources: Vec<Source> = Source::ALL.into_iter().filter(|s| t.tallies.contains_key(s)).collect();
    for &source in &sources {
        let t = tally(source);
        let f = |l: Level| t.level(l).map(|v| format!("{v:.1}")).unwrap_or_else(|| "-".into());
        let n: usize = t.by_level.values().map(|(_, n)| n).sum();
        println!(
            "| {} | {} | {} | {} | {:.1} | {n} |",
            source.label(),
            f(Level::View),
            f(Level::Object),
            f(Level::Scene),
            t.overall()
        );
    }
    find_report(t);
    let kinds: std::collections::BTreeSet<&String> = t.tallies.values().flat_map(|t| t.by_kind.keys()).collect();
    println!(
        "\n| question type | (a) ground truth | (b) rendered RGB | (c) ChatSplat | asked |\n|---|---|---|---|---|"
    );
    for k in &kinds {
        let pct = |s: Source| {
            tally(s)
                .by_kind
                .get(*k)
                .map(|(r, n)| format!("{:.1}", 100.0 * *r as f64 / (*n).max(1) as f64))
                .unwrap_or("-".into())
        };
        let n = sources.iter().find_map(|&s| tally(s).by_kind.get(*k)).map_or(0, |e| e.1);
        println!(
            "| {k} | {} | {} | {} | {n} |",
            pct(Source::GroundTruth),
            pct(Source::RenderedRgb),
            pct(Source::ChatSplat)
        );
    }
    let tallies: serde_json::Map<_, _> =
        t.tallies.iter().map(|(s, t)| (format!("{s:?}"), serde_json::to_value(t).unwrap())).collect();
    if t.seconds.is_empty() {
        // `--chatsplat-only`: no token figures
        return write_bench(t, settings, serde_json::json!({ "tallies": tallies }), out);
    }
    println!("\n| tokens of | views/s | objects/s | view token L1 vs teacher(GT) | cosine |\n|---|---|---|---|---|");
    let rate = |s: Source, l: Level| t.seconds.get(&(s, l)).map(|(t, n)| *n as f64 / t.max(1e-9));
    let fmt = |r: Option<f64>| r.map_or("-".into(), |r| format!("{r:.1}"));
    let (fr, fc) = (t.fid_rgb.mean(), t.fid_cs.mean());
    for (name, s, f) in [
        ("(b) render RGB + vision tower", Source::RenderedRgb, &fr),
        ("(c) ChatSplat: render language map + encoder", Source::ChatSplat, &fc),
    ] {
        println!(
            "| {name} | {} | {} | {:.4} | {:.4} |",
            fmt(rate(s, Level::View)),
            fmt(rate(s, Level::Object)),
            f.l1,
            f.cos
        );
    }
    let baseline = rate(Source::RenderedRgb, Level::View).map(|r| (r, tally(Source::RenderedRgb).overall()));
    if !t.points.is_empty() {
        sweep_report(&t.points, baseline, (&t.label(), t.scenes()), out)?;
    }
    let figures = serde_json::json!({
        "tallies": tallies,
        "token_seconds": t.seconds.iter().map(|(&(s, l), &(secs, n))| (s, l, secs, n)).collect::<Vec<_>>(),
        "fidelity_rendered_rgb": fr, "fidelity_chatsplat": fc, "sweep": t.points,
    });
    write_bench(t, settings, figures, out)
}

/// Writes bench.json: `settings`, then `figures` and the find tallies.
fn write_bench(
    t: &Totals,
    settings: serde_json::Value,
    figures: serde_json::Value,
    out: &std::path::Path,
) -> Result<()> {
    let mut json = settings;
    if let (Some(j), serde_json::Value::Object(f)) = (json.as_object_mut(), figures) {
        j.extend(f);
        j.insert("tallies".into(), j.get("tallies").cloned().unwrap_or_else(|| serde_json::json!({})));
        j.insert("find".into(), serde_json::to_value(&t.find).expect("plain numbers"));
        j.insert("find_seconds".into(), t.find_seconds.into());
    }
    model::io::write_json(&out.join("bench.json"), &json)?;
    println!("\nfigures -> {}", out.join("bench.json").display());
    Ok(())
}

/// Adds one scene's (or run's) find tallies by kind and seconds to `find` and `seconds`.
pub(crate) fn add_find(find: &mut FindKinds, seconds: &mut f64, kinds: &FindKinds, secs: f64) {
    for (k, t) in kinds {
        find.entry(k.clone()).or_default().merge(t);
    }
    *seconds += secs;
}

/// ChatSplat's find phrases: the summary over all, and a table by kind.
fn find_report(t: &Totals) {
    let mut all = FindTally::default();
    t.find.values().for_each(|k| all.merge(k));
    if all.phrases == 0 {
        return;
    }
    println!(
        "\n(c) ChatSplat {}; {:.1} ms a phrase (the first of each scene builds its finder)",
        all.summary(),
        1e3 * t.find_seconds / all.phrases as f64
    );
    println!("\n| find phrases | asked | precision | recall | F1 | exact (%) |\n|---|---|---|---|---|---|");
    for (k, f) in &t.find {
        let exact = 100.0 * f.exact as f32 / f.phrases.max(1) as f32;
        println!("| {k} | {} | {:.3} | {:.3} | {:.3} | {exact:.1} |", f.phrases, f.precision(), f.recall(), f.f1());
    }
}
