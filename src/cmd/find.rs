//! `chatsplat find`: the objects of a trained scene that match a phrase ("red cone"), scored
//! through the scene's own object tokens (`model::find`), best first; `--json` for scripts.

use super::SceneArgs;
use model::find::{DEFAULT_THRESHOLD, Finder, ObjectNames, check_threshold};

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// What to find, e.g. "red cone", "cube", "blue".
    pub phrase: String,
    /// Score (0-1) from which an object matches.
    #[arg(long, default_value_t = DEFAULT_THRESHOLD)]
    pub threshold: f32,
    /// Print `{"query", "threshold", "matches": [{"id", "name", "score"}]}` (the matches only,
    /// best first) instead of the table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let threshold = check_threshold(a.threshold).map_err(|e| anyhow::anyhow!("--threshold: {e}"))?;
    model::find::normalize(&a.phrase)?;
    let s = a.scene.open()?;
    let mut warnings = Vec::new();
    let names = ObjectNames::of_run(&a.scene.geometry(), &mut warnings);
    for w in warnings {
        model::error::warn(w);
    }
    let t0 = std::time::Instant::now();
    let mut finder = model::catch_backend("the object tokens", || Finder::new(&s, &names))??;
    let t1 = std::time::Instant::now();
    let ranked = model::catch_backend("scoring", || finder.rank(&s, &a.phrase))??;
    let t2 = std::time::Instant::now();
    let matches: Vec<_> = ranked.iter().filter(|r| r.score >= threshold).collect();
    if a.json {
        let matches: Vec<_> = matches
            .iter()
            .map(|r| serde_json::json!({"id": r.id, "name": names.name(r.id), "score": r.score}))
            .collect();
        println!("{}", serde_json::json!({"query": a.phrase, "threshold": threshold, "matches": matches}));
        return Ok(());
    }
    eprintln!(
        "{} objects: their tokens in {:.0} ms, scored in {:.0} ms",
        ranked.len(),
        (t1 - t0).as_secs_f64() * 1e3,
        (t2 - t1).as_secs_f64() * 1e3
    );
    println!("{:>4}  {:<20} {:>6}  as the answer to", "id", "name", "score");
    for r in &ranked {
        let mark = if r.score >= threshold { "  <- match" } else { "" };
        println!("{:>4}  {:<20} {:>6.3}  {}{mark}", r.id, names.name(r.id), r.score, r.question);
    }
    match matches.len() {
        0 => println!("nothing matches \"{}\" (threshold {threshold})", a.phrase),
        n => println!("{n} match(es) for \"{}\" (threshold {threshold})", a.phrase),
    }
    Ok(())
}
