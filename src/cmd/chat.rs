//! `chatsplat chat`: an interactive session with a trained scene.

use super::{SceneArgs, print_piece};
use model::chat::{ChatSession, Conversation, DEFAULT_SCENE_VIEWS, Target};
use std::io::BufRead;

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub scene: SceneArgs,
    #[arg(long, default_value_t = 256)]
    pub max_new_tokens: usize,
}

const HELP: &str = "commands: :view N (view level) | :click X Y (object level, in the current view) | \
    :scene [K] (scene level) | :new (a new conversation, same target) | :show (write the current view PNG) | \
    :help | :quit; anything else is a question, asked after the conversation's earlier ones (a new target \
    starts a new conversation)";

/// One line of input, parsed.
enum Line {
    Empty,
    Quit,
    Help,
    View(usize),
    Click(usize, usize),
    Scene(usize),
    New,
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
        Some(":scene") if words.len() == 1 => Line::Scene(0), // the default, resolved against the scene
        Some(":scene") => match num(1, ":scene [K] with K >= 1")? {
            0 => return Err("usage: :scene [K] with K >= 1".into()),
            k => Line::Scene(k),
        },
        Some(":show") => Line::Show,
        Some(":new") => Line::New,
        Some(w) if w.starts_with(':') => return Err(format!("unknown command {w}; {HELP}")),
        Some(_) => Line::Question(line.to_string()),
    })
}

/// Where the conversation is: the current view and the conversation about its target.
struct State {
    view: usize,
    conversation: Conversation,
    /// How the prompt names the target.
    label: String,
}

impl State {
    fn new(view: usize, target: Target, label: String) -> Self {
        Self { view, conversation: Conversation::new(target), label }
    }
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let s = a.scene.open()?;
    s.check_max_new_tokens("--max-new-tokens", a.max_new_tokens)?;
    eprintln!("{} views ({} training), {} Gaussians. {HELP}", s.cameras.len(), s.train_views, s.scene.field.len());
    let opts = model::vlm::GenerateOptions { max_new_tokens: a.max_new_tokens, ..Default::default() };
    // a model trained on single questions gets each question on its own
    let converses = s.vlm.converses();
    if !converses {
        eprintln!("note: {}", model::vlm::conversation::SINGLE_TURN_NOTE);
    }
    let names = model::find::ObjectNames::of_run(&a.scene.geometry(), &mut Vec::new());
    let forms = known_forms(&s, &names.objects());
    if let Some(forms) = &forms {
        eprintln!("{forms}");
    }
    let mut state = State::new(0, Target::View(*s.camera(0)?), "view 0".into());
    eprint!("[{}] > ", state.label);
    let mut input = std::io::stdin().lock();
    let mut bytes = Vec::new();
    loop {
        bytes.clear();
        if input.read_until(b'\n', &mut bytes).map_err(|e| anyhow::anyhow!("stdin: {e}"))? == 0 {
            break;
        }
        // a line that is not UTF-8 (a paste in another encoding) is refused, not the session
        let Ok(text) = std::str::from_utf8(&bytes) else {
            eprintln!("error: that line is not UTF-8 text; nothing was asked");
            eprint!("[{}] > ", state.label);
            continue;
        };
        let line = text.trim_end_matches(['\n', '\r']);
        match parse(line) {
            Ok(Line::Quit) => break,
            Ok(cmd) => {
                if let (Line::Help, Some(forms)) = (&cmd, &forms) {
                    eprintln!("{forms}");
                }
                if let Err(e) = apply(&s, cmd, &mut state, &opts, converses) {
                    eprintln!("error: {e}");
                }
            }
            Err(e) => eprintln!("{e}"),
        }
        eprint!("[{}] > ", state.label);
    }
    eprintln!();
    Ok(())
}

/// Runs one line; `converses`: whether questions follow the conversation (else each is asked on
/// its own).
fn apply(
    s: &ChatSession,
    cmd: Line,
    state: &mut State,
    opts: &model::vlm::GenerateOptions,
    converses: bool,
) -> model::Result<()> {
    match cmd {
        Line::Empty | Line::Quit => {}
        Line::Help => eprintln!("{HELP}"),
        Line::View(v) => {
            *state = State::new(v, Target::View(*s.camera(v)?), format!("view {v}"));
        }
        // one identity render picks the object; its tokens are computed at the first question
        // and kept for the follow-ups
        Line::Click(x, y) => match s.click(s.camera(state.view)?, x, y)? {
            Some(p) => {
                let path = s.language.picked(state.view, p.id);
                s.show(&p.camera, Some(&p), &path)?;
                eprintln!("object {} picked; highlighted -> {}", p.id, path.display());
                let label = format!("view {} object {}", state.view, p.id);
                *state = State::new(state.view, Target::Object(p), label);
            }
            None => eprintln!("pixel ({x}, {y}) shows no object"),
        },
        Line::Scene(k) => {
            let k = if k == 0 { DEFAULT_SCENE_VIEWS.min(s.train_views) } else { k };
            *state = State::new(state.view, s.scene_target(k)?, format!("scene, {k} views"));
        }
        Line::New => {
            state.conversation = Conversation::new(state.conversation.target.clone());
            eprintln!("new conversation about {}", state.conversation.target);
        }
        Line::Show => {
            let path = s.language.view_png(state.view);
            s.show(s.camera(state.view)?, None, &path)?;
            eprintln!("-> {}", path.display());
        }
        Line::Question(q) => {
            if !converses {
                state.conversation = Conversation::new(state.conversation.target.clone());
            }
            if let Some(note) = model::known::unknown_question_note(&s.vlm, &state.conversation.target, &q) {
                eprintln!("note: {note}");
            }
            let reply = model::catch_backend("generation", || {
                s.converse_until(&mut state.conversation, &q, opts, |piece| {
                    print_piece(piece);
                    std::ops::ControlFlow::Continue(())
                })
            })??;
            println!();
            if let Some(note) = reply.dropped_note() {
                eprintln!("note: {note}");
            }
        }
    }
    Ok(())
}

/// The questions a model trained on the synthetic forms knows, about this scene's objects, one
/// line per level; `None` for a model that takes any question.
fn known_forms(s: &ChatSession, objects: &[String]) -> Option<String> {
    let examples = model::known::examples(&s.vlm, objects)?;
    let mut out = String::from("this model was trained on these questions (others get a guess):");
    for level in [model::vqa::Level::View, model::vqa::Level::Object, model::vqa::Level::Scene] {
        let at: Vec<&str> = examples.iter().filter(|(l, _)| *l == level).map(|(_, q)| q.as_str()).collect();
        out += &format!("\n  {level}: {}", at.join(" | "));
    }
    Some(out)
}
