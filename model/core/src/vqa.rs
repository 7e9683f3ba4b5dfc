//! Answering a question file ([`crate::question_file`]) through a [`ChatSession`]: what each
//! question asks about (a view, a clicked object, several views) and the runner; a `find`
//! question's phrase is searched for among the scene's objects ([`crate::find`]).

use crate::ObjectId;
use crate::chat::{ChatSession, Conversation, Target};
use crate::error::{Error, Result};
use crate::find::{Finder, ObjectNames};
use crate::vlm::GenerateOptions;
use std::collections::{HashMap, HashSet};
use std::ops::ControlFlow;

pub use crate::question_file::{Level, Question, QuestionFile, load_questions, scene_view};

/// One answered question.
#[derive(Clone, Debug, PartialEq)]
pub struct Answer {
    /// The generated text, or why the question could not be asked (an invalid view or click).
    pub text: std::result::Result<String, String>,
    /// The object the click picked (object level).
    pub picked: Option<ObjectId>,
    /// Find level: the ids of the objects found, best first.
    pub found: Option<Vec<ObjectId>>,
}

/// How a question file's `find` questions are searched.
#[derive(Clone, Debug)]
pub struct FindOptions {
    /// The scene's objects by name (which objects a search looks at: not a synthetic scene's table).
    pub names: ObjectNames,
    /// Score from which an object is found.
    pub threshold: f32,
}

impl FindOptions {
    /// The names of the run the session was opened on ([`ObjectNames::of_run`]), and the default
    /// threshold.
    pub fn of_run(run: &crate::run::GeometryRun, warnings: &mut Vec<String>) -> Self {
        Self { names: ObjectNames::of_run(run, warnings), threshold: crate::find::DEFAULT_THRESHOLD }
    }
}

/// A find question's objects found: the phrase ranked over the objects of `finder` (made at the
/// first call and kept), those at or above the threshold.
pub fn find_objects(
    session: &ChatSession,
    finder: &mut Option<Finder>,
    opts: &FindOptions,
    phrase: &str,
) -> Result<Vec<ObjectId>> {
    let f = match finder {
        Some(f) => f,
        None => finder.insert(Finder::new(session, &opts.names)?),
    };
    Ok(crate::find::matches(&f.rank(session, phrase)?, opts.threshold))
}

/// What a question asks about; `scene_views` spread views for scene questions without `views`.
/// An object question's click is resolved here: a click on no object is an error.
pub fn target_of(file: &QuestionFile, q: &Question, session: &ChatSession, scene_views: usize) -> Result<Target> {
    let view = |v: Option<usize>| scene_view(file, &session.images, v.unwrap_or(0));
    Ok(match q.level {
        Level::View => Target::View(*session.camera(view(q.view)?)?),
        Level::Scene => match &q.views {
            Some(v) => Target::Scene(
                v.iter()
                    .map(|&i| Ok(*session.camera(scene_view(file, &session.images, i)?)?))
                    .collect::<Result<_>>()?,
            ),
            None => session.scene_target(scene_views)?,
        },
        Level::Find => return Err(Error::input("a find question has no target: its phrase is searched for")),
        Level::Object => {
            let v = view(q.view)?;
            let [x, y] = q.object.unwrap_or([0.0, 0.0]).map(|c| c as usize);
            match session.click(session.camera(v)?, x, y)? {
                Some(p) => Target::Object(p),
                None => return Err(Error::input(format!("pixel ({x}, {y}) of view {v} shows no object"))),
            }
        }
    })
}

/// The conversation `q` is asked in: a copy of the one of the question it follows (after that
/// question and its answer), or a new one about its target.
fn conversation_of(
    file: &QuestionFile,
    q: &Question,
    session: &ChatSession,
    scene_views: usize,
    kept: &HashMap<&str, Conversation>,
) -> Result<Conversation> {
    match &q.follows {
        Some(first) => kept
            .get(first.as_str())
            .cloned()
            .ok_or_else(|| Error::input(format!("it follows {first:?}, which could not be asked"))),
        None => Ok(Conversation::new(target_of(file, q, session, scene_views)?)),
    }
}

/// Answers every question of `file` (greedy unless `opts` says otherwise; `find` questions
/// searched as `find` says; a question that follows another asked after it and the model's
/// answer to it), calling `on_answer(index, question, answer)` after each. A question
/// that cannot be asked (a view that does not exist, a click on no object, a search in a scene
/// trained without masks) gets an `Err` text; backend failures stop the run.
pub fn answer_all(
    session: &ChatSession,
    file: &QuestionFile,
    opts: &GenerateOptions,
    scene_views: usize,
    find: &FindOptions,
    mut on_answer: impl FnMut(usize, &Question, &Answer),
) -> Result<Vec<Answer>> {
    let mut out = Vec::with_capacity(file.questions.len());
    let mut finder = None;
    // the conversations that later questions follow, by the id of their question
    let followed: HashSet<&str> = file.questions.iter().filter_map(|q| q.follows.as_deref()).collect();
    let mut kept: HashMap<&str, Conversation> = HashMap::new();
    for (i, q) in file.questions.iter().enumerate() {
        let a = if q.level == Level::Find {
            match find_objects(session, &mut finder, find, &q.question) {
                Ok(ids) => {
                    let names: Vec<String> = ids.iter().map(|&id| find.names.name(id)).collect();
                    let text = if names.is_empty() { "none".to_string() } else { names.join(", ") };
                    Answer { text: Ok(text), picked: None, found: Some(ids) }
                }
                Err(e @ (Error::Backend { .. } | Error::Io { .. })) => return Err(e),
                Err(e) => Answer { text: Err(e.to_string()), picked: None, found: None },
            }
        } else {
            let asked = conversation_of(file, q, session, scene_views, &kept).and_then(|mut c| {
                let picked = if let Target::Object(p) = &c.target { Some(p.id) } else { None };
                let reply = session.converse_until(&mut c, &q.question, opts, |_| ControlFlow::Continue(()))?;
                if followed.contains(q.id.as_str()) {
                    kept.insert(q.id.as_str(), c);
                }
                Ok((reply.generation, picked))
            });
            match asked {
                Ok((g, picked)) => Answer { text: Ok(g.text), picked, found: None },
                Err(e @ (Error::Backend { .. } | Error::Io { .. })) => return Err(e),
                Err(e) => Answer { text: Err(e.to_string()), picked: None, found: None },
            }
        };
        on_answer(i, q, &a);
        out.push(a);
    }
    Ok(out)
}
