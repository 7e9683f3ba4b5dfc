//! Answering a question file ([`crate::question_file`]) through a [`ChatSession`]: what each
//! question asks about (a view, a clicked object, several views) and the runner.

use crate::chat::{ChatSession, Target};
use crate::error::{Error, Result};
use crate::vlm::GenerateOptions;

pub use crate::question_file::{Level, Question, QuestionFile, load_questions, scene_view};

/// One answered question.
#[derive(Clone, Debug, PartialEq)]
pub struct Answer {
    /// The generated text, or why the question could not be asked (an invalid view or click).
    pub text: std::result::Result<String, String>,
    /// The object the click picked (object level).
    pub picked: Option<u8>,
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

/// Answers every question of `file` (greedy unless `opts` says otherwise), calling
/// `on_answer(index, question, answer)` after each. A question that cannot be asked (a view that
/// does not exist, a click on no object) gets an `Err` text; backend failures stop the run.
pub fn answer_all(
    session: &ChatSession,
    file: &QuestionFile,
    opts: &GenerateOptions,
    scene_views: usize,
    mut on_answer: impl FnMut(usize, &Question, &Answer),
) -> Result<Vec<Answer>> {
    let mut out = Vec::with_capacity(file.questions.len());
    for (i, q) in file.questions.iter().enumerate() {
        let asked = target_of(file, q, session, scene_views).and_then(|t| {
            let picked = if let Target::Object(p) = &t { Some(p.id) } else { None };
            Ok((session.ask(&t, &q.question, opts, |_| {})?, picked))
        });
        let a = match asked {
            Ok((g, picked)) => Answer { text: Ok(g.text), picked },
            Err(e @ (Error::Backend { .. } | Error::Io { .. })) => return Err(e),
            Err(e) => Answer { text: Err(e.to_string()), picked: None },
        };
        on_answer(i, q, &a);
        out.push(a);
    }
    Ok(out)
}
