//! Question files about a scene (the paper's view / object / scene-level question answering): the
//! types, reading and validating them, and which scene view an index means. Answering them
//! through a chat session is `model::vqa`'s; scoring is `scoring::score`'s. A leaf: the synthetic
//! scenes ([`crate::synth`]) write these files.
//!
//! # Question files
//!
//! ```json
//! {"scene": "room",
//!  "questions": [
//!   {"id": "q1", "level": "view", "view": 3,
//!    "question": "What colour is the cube?", "answer": "red", "keywords": ["red"]},
//!   {"id": "q2", "level": "object", "view": 0, "object": [120, 64],
//!    "question": "What is this object?", "answer": "a wooden chair"},
//!   {"id": "q3", "level": "scene", "question": "How many chairs are there?", "answer": "two"},
//!   {"id": "q4", "level": "scene", "question": "What objects are there?",
//!    "answer": "red chair red cup", "items": ["red chair", "red cup"]},
//!   {"id": "f1", "level": "find", "question": "red cone", "answer": "red cone", "objects": [3]},
//!   {"id": "q5", "level": "object", "view": 0, "object": [120, 64], "follows": "q2",
//!    "question": "What color is it?", "answer": "brown"}
//! ]}
//! ```
//!
//! `scene` is optional. `level` is `view`, `object`, `scene` or `find`; `view` (an image index) is
//! required for view-level questions; `object` (an `[x, y]` pixel, in the image of `view` when
//! given) is required for object-level ones; scene-level questions may list their `views`
//! (default: views spread around the scene); `keywords` is optional. `items` marks a list answer
//! and names its items (`[]` for an answer of "none"): a list is scored as a multiset of items, so
//! an item missed or an item invented is never right. A `find` question is a phrase to search the
//! scene's objects for (`chatsplat find`): `objects` lists the instance ids of the objects it
//! names (`[]`: none), `answer` their names or "none"; it takes no view, click or views. A
//! question that `follows` an earlier one (its id) is asked as the next turn of that question's
//! conversation, after it and the model's answer to it: the same level, view, click and views;
//! its `spelled` names the same question with its referent spelled out. Ids must be unique and the question and
//! answer texts non-empty. Unknown keys are rejected (typos).

use crate::ObjectId;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::path::Path;

/// Views a scene-level question is asked from: the views the synthetic question files name for
/// each (chosen to see every object together), the views chat spreads around the scene when not
/// told how many, and the images per scene the built-in model was trained with.
pub const SCENE_VIEWS: usize = 4;

/// The granularity a question asks about.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Level {
    View,
    Object,
    Scene,
    /// A phrase searched for among the scene's objects (`chatsplat find`), scored by the objects
    /// found (precision, recall, F1), not by an answer's words.
    Find,
}

impl Level {
    /// The levels answered in words, scored by exact match: not [`Level::Find`].
    pub const ANSWERED: [Level; 3] = [Level::View, Level::Object, Level::Scene];
}

impl std::fmt::Display for Level {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Level::View => "view",
            Level::Object => "object",
            Level::Scene => "scene",
            Level::Find => "find",
        })
    }
}

/// One annotated question with its reference answer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Question {
    pub id: String,
    pub level: Level,
    /// The question type (free text, e.g. `count`; scores are also reported per kind).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kind: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub view: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub object: Option<[f32; 2]>,
    /// Scene level: the views to use (default: views spread around the scene).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub views: Option<Vec<usize>>,
    pub question: String,
    pub answer: String,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub keywords: Vec<String>,
    /// A list answer's items (a multiset; empty for "none"); `None` when the answer is not a list.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub items: Option<Vec<String>>,
    /// Find level: the instance ids of the objects the phrase names (empty: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub objects: Option<Vec<ObjectId>>,
    /// The id of an earlier question about the same target whose conversation this one goes on
    /// (asked after it and the model's answer).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub follows: Option<String>,
    /// A follow-up's twin: the id of the same question with its referent spelled out, asked on
    /// its own (`vqa` reports the follow-ups' exact match beside their twins').
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spelled: Option<String>,
}

/// A question file: see the [module documentation](self) for the format.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct QuestionFile {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene: Option<String>,
    /// The dataset's images in frame order (transforms.json): `view` indexes this list and the
    /// images are found among the trained scene's views by file name. Without it, `view` indexes
    /// the scene's views directly (training views, then held-out views).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub views: Option<Vec<String>>,
    pub questions: Vec<Question>,
}

/// Reads and validates a question file; errors name the file and the problem.
pub fn load_questions(path: &Path) -> Result<QuestionFile> {
    let file: QuestionFile = crate::io::read_json_object(path, r#"{"questions": [...]} (a "scene" name optional)"#)?;
    if file.questions.is_empty() {
        return Err(Error::invalid(path, "holds no questions"));
    }
    let mut seen = HashSet::new();
    for (i, q) in file.questions.iter().enumerate() {
        let fail = |what: &str| Err(Error::invalid(path, format!("question {i} (id {:?}): {what}", q.id)));
        if q.id.trim().is_empty() {
            return fail("empty id");
        }
        if !seen.insert(q.id.as_str()) {
            return fail("duplicate id");
        }
        if q.question.trim().is_empty() {
            return fail("empty question text");
        }
        if q.answer.trim().is_empty() {
            return fail("empty reference answer");
        }
        if q.level == Level::View && q.view.is_none() {
            return fail("view-level question without \"view\"");
        }
        if q.level == Level::Object && q.object.is_none() {
            return fail("object-level question without \"object\" pixel");
        }
        // as the viewer's API: a field of another level is a mistake, not something to ignore
        if q.level != Level::Object && q.object.is_some() {
            return fail(&format!("\"object\" does not apply to {}-level questions", q.level));
        }
        if q.level != Level::Scene && q.views.is_some() {
            return fail(&format!("\"views\" does not apply to {}-level questions", q.level));
        }
        if let Some([x, y]) = q.object
            && !(x.is_finite() && y.is_finite() && x >= 0.0 && y >= 0.0)
        {
            return fail("\"object\" pixel must be two non-negative numbers");
        }
        if q.level == Level::Find && q.objects.is_none() {
            return fail("find-level question without \"objects\" (the ids it names; [] for none)");
        }
        if q.level != Level::Find && q.objects.is_some() {
            return fail(&format!("\"objects\" does not apply to {}-level questions", q.level));
        }
        if q.level == Level::Find && (q.view.is_some() || q.items.is_some()) {
            return fail("\"view\" and \"items\" do not apply to find-level questions");
        }
        if let Some(ids) = &q.objects {
            if ids.contains(&0) {
                return fail("\"objects\" names 0, the background: objects are 1 and up");
            }
            if let Some(d) = ids.iter().enumerate().find_map(|(k, id)| ids[..k].contains(id).then_some(id)) {
                return fail(&format!("\"objects\" names object {d} twice"));
            }
        }
        if let Some(first) = &q.follows {
            let Some(f) = file.questions[..i].iter().find(|p| p.id == *first) else {
                return fail(&format!("\"follows\" names {first:?}, which is not an earlier question"));
            };
            if q.level == Level::Find || (f.level, f.view, f.object, &f.views) != (q.level, q.view, q.object, &q.views)
            {
                return fail(&format!(
                    "\"follows\" {first:?}, a question about another target: a follow-up asks \
                    about the same level, view, click and views"
                ));
            }
        }
        if let Some(twin) = &q.spelled {
            if q.follows.is_none() {
                return fail("\"spelled\" applies only to a question that \"follows\" another");
            }
            let Some(t) = file.questions.iter().find(|p| p.id == *twin && p.follows.is_none()) else {
                return fail(&format!(
                    "\"spelled\" names {twin:?}, which is not a question of the file asked on its own"
                ));
            };
            // the twin asks the same thing of the same target, the referent spelled out
            if (t.level, t.view, t.object, &t.views) != (q.level, q.view, q.object, &q.views) {
                return fail(&format!(
                    "\"spelled\" names {twin:?}, a question about another target: a follow-up's twin asks \
                    about the same level, view, click and views"
                ));
            }
        }
        if q.views.as_ref().is_some_and(|v| v.is_empty()) {
            return fail("\"views\" is empty");
        }
        if q.items.iter().flatten().any(|i| i.trim().is_empty()) {
            return fail("an empty item in \"items\"");
        }
        if let Some(frames) = &file.views {
            let n = frames.len();
            if q.view.is_some_and(|v| v >= n) || q.views.iter().flatten().any(|&v| v >= n) {
                return fail(&format!("a view index is not below the {n} listed views"));
            }
        }
    }
    Ok(file)
}

/// Refuses a question file (read from `path`) that names another scene than the dataset in
/// `data` (the data a run was trained on): the dataset's own `questions.json` names its scene (as
/// `chatsplat synth` writes it); a file that names none, or a dataset without its own file, is
/// taken as it is.
pub fn check_scene(file: &QuestionFile, path: &Path, data: &Path) -> Result<()> {
    let own = data.join("questions.json");
    let Some(name) = &file.scene else { return Ok(()) };
    if !own.is_file() || crate::io::resolved(&own) == crate::io::resolved(path) {
        return Ok(());
    }
    let theirs = crate::io::read_json::<QuestionFile>(&own).ok().and_then(|f| f.scene);
    match theirs {
        Some(t) if t != *name => Err(Error::invalid(
            path,
            format!(
                "is about the scene \"{name}\", but the run was trained on {}, whose questions.json is about \
                 \"{t}\": give a question file of this scene",
                data.display()
            ),
        )),
        _ => Ok(()),
    }
}

/// The scene view a question's view index means: through the file's frame list (by image file
/// name, among `images`, the run's view image names) when it has one, else the index itself.
pub fn scene_view(file: &QuestionFile, images: &[String], view: usize) -> Result<usize> {
    let Some(frames) = &file.views else { return Ok(view) };
    let frame = frames.get(view).ok_or_else(|| Error::input(format!("view {view} is not in the file's views")))?;
    let name = Path::new(frame).file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    images
        .iter()
        .position(|i| *i == name)
        .ok_or_else(|| Error::input(format!("frame {view} ({frame}) is not one of the trained scene's views")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str, text: &str) -> std::path::PathBuf {
        let p = std::env::temp_dir().join(format!("chatsplat-vqa-{}-{name}.json", std::process::id()));
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn question_files() {
        let good = r#"{"scene": "room", "questions": [
            {"id": "q1", "level": "view", "view": 3, "question": "Colour?", "answer": "red", "keywords": ["red"]},
            {"id": "q2", "level": "object", "object": [1.5, 2], "question": "What?", "answer": "chair"},
            {"id": "q3", "level": "scene", "question": "How many?", "answer": "two"}]}"#;
        let p = tmp("good", good);
        let f = load_questions(&p).unwrap();
        let _ = std::fs::remove_file(p);
        assert_eq!(f.scene.as_deref(), Some("room"));
        assert_eq!(f.questions.len(), 3);
        assert_eq!((f.questions[0].level, f.questions[0].view), (Level::View, Some(3)));
        assert_eq!(f.questions[1].object, Some([1.5, 2.0]));
        assert!(f.questions[2].keywords.is_empty());

        let err = |name: &str, text: &str| {
            let p = tmp(name, text);
            let e = load_questions(&p).unwrap_err().to_string();
            let _ = std::fs::remove_file(&p);
            assert!(e.contains(&p.display().to_string()), "{e}");
            e
        };
        let q = |body: &str| format!(r#"{{"questions": [{body}]}}"#);
        let e = err("json", "{\"questions\": [\n  {\"id\": }]}");
        assert!(e.contains("line 2, column"), "{e}");
        let e = err("obj", &q(r#"{"id": "a", "level": "object", "question": "Q?", "answer": "x"}"#));
        assert!(e.contains("\"a\"") && e.contains("without \"object\""), "{e}");
        let e = err("view", &q(r#"{"id": "b", "level": "view", "question": "Q?", "answer": "x"}"#));
        assert!(e.contains("without \"view\""), "{e}");
        let e = err("empty", &q(r#"{"id": "c", "level": "scene", "question": " ", "answer": "x"}"#));
        assert!(e.contains("empty question"), "{e}");
        let one = r#"{"id": "d", "level": "scene", "question": "Q?", "answer": "x"}"#;
        let e = err("dup", &q(&format!("{one}, {one}")));
        assert!(e.contains("question 1") && e.contains("duplicate id"), "{e}");
        let e = err("level", &q(r#"{"id": "e", "level": "room", "question": "Q?", "answer": "x"}"#));
        assert!(e.contains("invalid JSON") && e.contains("room"), "{e}");
        let e = err("top", &format!("[{one}]"));
        assert!(e.contains("the top level is an array") && e.contains(r#"{"questions": [...]}"#), "{e}");
        let e = err(
            "viewobj",
            &q(r#"{"id": "f", "level": "view", "view": 0, "object": [1, 2], "question": "Q?", "answer": "x"}"#),
        );
        assert!(e.contains("\"object\" does not apply to view-level"), "{e}");
        let e = err(
            "objviews",
            &q(r#"{"id": "g", "level": "object", "object": [1, 2], "views": [0], "question": "Q?", "answer": "x"}"#),
        );
        assert!(e.contains("\"views\" does not apply to object-level"), "{e}");
        let e =
            err("items", &q(r#"{"id": "h", "level": "scene", "question": "Q?", "answer": "x", "items": ["x", " "]}"#));
        assert!(e.contains("empty item"), "{e}");
        let e = err("findobj", &q(r#"{"id": "j", "level": "find", "question": "red cone", "answer": "red cone"}"#));
        assert!(e.contains("\"j\"") && e.contains("without \"objects\""), "{e}");
        let e = err(
            "viewids",
            &q(r#"{"id": "k", "level": "view", "view": 0, "question": "Q?", "answer": "x", "objects": [1]}"#),
        );
        assert!(e.contains("\"objects\" does not apply to view-level"), "{e}");
        let e = err(
            "findview",
            &q(r#"{"id": "l", "level": "find", "view": 0, "question": "cone", "answer": "none", "objects": []}"#),
        );
        assert!(e.contains("do not apply to find-level"), "{e}");
        let find =
            q(r#"{"id": "m", "level": "find", "question": "red cone", "answer": "red cone", "objects": [3, 5]}"#);
        let p = tmp("find", &find);
        let f = load_questions(&p).unwrap();
        let _ = std::fs::remove_file(p);
        assert_eq!((f.questions[0].level, f.questions[0].objects.clone()), (Level::Find, Some(vec![3, 5])));
        let first = concat!(
            r#"{"id": "n", "level": "object", "view": 1, "object": [3, 4], "#,
            r#""question": "What is this?", "answer": "red cube"}"#
        );
        let twin = concat!(
            r#"{"id": "c", "level": "object", "view": 1, "object": [3, 4], "#,
            r#""question": "What color is this?", "answer": "red"}"#
        );
        let follow = |target: &str, follows: &str| {
            let head = r#"{"id": "f", "level": "object", "#;
            format!(r#"{head}{target}, "question": "What color is it?", "answer": "red", {follows}}}"#)
        };
        let at = r#""view": 1, "object": [3, 4]"#;
        let good = q(&format!("{first}, {twin}, {}", follow(at, r#""follows": "n", "spelled": "c""#)));
        let p = tmp("follows", &good);
        let f = load_questions(&p).unwrap();
        let _ = std::fs::remove_file(p);
        assert_eq!((f.questions[2].follows.as_deref(), f.questions[2].spelled.as_deref()), (Some("n"), Some("c")));
        let e = err("later", &q(&format!("{}, {first}", follow(at, r#""follows": "n""#))));
        assert!(e.contains("not an earlier question"), "{e}");
        let e = err(
            "elsewhere",
            &q(&format!("{first}, {}", follow(r#""view": 2, "object": [3, 4]"#, r#""follows": "n""#))),
        );
        assert!(e.contains("about another target"), "{e}");
        let e = err("twin", &q(&format!("{first}, {}", follow(at, r#""follows": "n", "spelled": "zz""#))));
        assert!(e.contains("\"spelled\" names \"zz\""), "{e}");
        let e = err("alone", &q(&format!("{first}, {}", follow(at, r#""spelled": "n""#))));
        assert!(e.contains("applies only to a question that"), "{e}");
        let list = q(r#"{"id": "i", "level": "scene", "question": "Q?", "answer": "none", "items": []}"#);
        let p = tmp("list", &list);
        let f = load_questions(&p).unwrap();
        let _ = std::fs::remove_file(p);
        assert_eq!(f.questions[0].items, Some(vec![]));
        let missing = std::env::temp_dir().join("chatsplat-vqa-no-such-file.json");
        let e = load_questions(&missing).unwrap_err().to_string();
        assert!(e.contains("no-such-file") && e.contains("cannot read"), "{e}");
    }
}
