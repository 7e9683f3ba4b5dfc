//! `chatsplat chat`: an interactive session with a trained scene.

use super::{SceneArgs, print_piece};
use model::chat::{ChatSession, Target};
use std::io::BufRead;

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub scene: SceneArgs,
    #[arg(long, default_value_t = 256)]
    pub max_new_tokens: usize,
}

const HELP: &str = "commands: :view N (view level) | :click X Y (object level, in the current view) | \
    :scene [K] (scene level) | :show (write the current view PNG) | :help | :quit; anything else is a question";

/// One line of input, parsed.
enum Line {
    Empty,
    Quit,
    Help,
    View(usize),
    Click(usize, usize),
    Scene(usize),
    Show,
    Question(String),
}

fn parse(line: &str) -> Result<Line, String> {
    let words: Vec<&str> = line.split_whitespace().collect();
    let num = |i: usize, usage: &str| -> Result<usize, String> {
        words.get(i).and_then(|w| w.parse::<usize>().ok()).ok_or_else(|| format!("usage: {usage}"))
    };
    Ok(match words.first().copied() {
        None => Line::Empty,
        Some(":quit" | ":q") => Line::Quit,
        Some(":help") => Line::Help,
        Some(":view") => Line::View(num(1, ":view N")?),
        Some(":click") => Line::Click(num(1, ":click X Y")?, num(2, ":click X Y")?),
        Some(":scene") if words.len() == 1 => Line::Scene(4),
        Some(":scene") => match num(1, ":scene [K] with K >= 1")? {
            0 => return Err("usage: :scene [K] with K >= 1".into()),
            k => Line::Scene(k),
        },
        Some(":show") => Line::Show,
        Some(w) if w.starts_with(':') => return Err(format!("unknown command {w}; {HELP}")),
        Some(_) => Line::Question(line.to_string()),
    })
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let s = a.scene.open()?;
    eprintln!("{} views ({} training), {} Gaussians. {HELP}", s.cameras.len(), s.train_views, s.scene.field.len());
    let opts = model::vlm::GenerateOptions { max_new_tokens: a.max_new_tokens, ..Default::default() };
    let mut view = 0usize;
    let mut target = Target::View(0);
    eprint!("[view 0] > ");
    for line in std::io::stdin().lock().lines() {
        let line = line.map_err(|e| anyhow::anyhow!("stdin: {e}"))?;
        match parse(&line) {
            Ok(Line::Quit) => break,
            Ok(cmd) => {
                if let Err(e) = apply(&s, cmd, &mut view, &mut target, &opts) {
                    eprintln!("error: {e}");
                }
            }
            Err(e) => eprintln!("{e}"),
        }
        eprint!("[{target}] > ");
    }
    eprintln!();
    Ok(())
}

fn apply(
    s: &ChatSession,
    cmd: Line,
    view: &mut usize,
    target: &mut Target,
    opts: &model::vlm::GenerateOptions,
) -> model::Result<()> {
    match cmd {
        Line::Empty | Line::Quit => {}
        Line::Help => eprintln!("{HELP}"),
        Line::View(v) => {
            s.camera(v)?;
            *view = v;
            *target = Target::View(v);
        }
        Line::Click(x, y) => match s.scene.pick(s.camera(*view)?, x, y)? {
            Some((id, _)) => {
                let path = s.language.picked(*view, id);
                s.show(*view, Some(id), &path)?;
                eprintln!("object {id} picked; highlighted -> {}", path.display());
                *target = Target::Object { view: *view, x, y };
            }
            None => eprintln!("pixel ({x}, {y}) shows no object"),
        },
        Line::Scene(k) => *target = Target::Scene(s.scene_views(k)?),
        Line::Show => {
            let path = s.language.view_png(*view);
            s.show(*view, None, &path)?;
            eprintln!("-> {}", path.display());
        }
        Line::Question(q) => {
            model::catch_backend("generation", || s.ask(target, &q, opts, print_piece))??;
            println!();
        }
    }
    Ok(())
}
