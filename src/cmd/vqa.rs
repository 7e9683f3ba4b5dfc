//! `chatsplat vqa`: answer a question file about a trained scene and score the answers.

use super::SceneArgs;
use model::ObjectId;
use model::chat::ChatSession;
use model::find::{FindTally, ObjectNames, check_threshold};
use model::vqa::{FindOptions, Level, QuestionFile, answer_all, load_questions};
use scoring::progress::Progress;
use scoring::score::{Grader, Summary, offline_score, summarize};
use serde::Serialize;
use std::path::{Path, PathBuf};

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// Question file (`chatsplat synth` writes DATA/questions.json).
    #[arg(long)]
    pub questions: PathBuf,
    /// Answers and scores as JSON (default: LANGUAGE/vqa.json).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub scoring: Scoring,
}

/// How a question file is asked and reported.
#[derive(clap::Args)]
pub struct Scoring {
    /// Scene-level questions without their own views use this many views spread around the scene.
    #[arg(long, default_value_t = model::chat::DEFAULT_SCENE_VIEWS)]
    pub views: usize,
    #[arg(long, default_value_t = 64)]
    pub max_new_tokens: usize,
    /// Print every question with its answer and the reference.
    #[arg(long)]
    pub show: bool,
    /// Score the rest when a question cannot be asked (a view that does not exist, a click on no
    /// object) instead of failing.
    #[arg(long)]
    pub keep_going: bool,
    /// Find-level questions: the score (0-1) from which an object is found, as `find --threshold`.
    #[arg(long, default_value_t = model::find::DEFAULT_THRESHOLD)]
    pub find_threshold: f32,
}

/// One row of `vqa.json`.
#[derive(Serialize)]
struct Row {
    id: String,
    level: Level,
    question: String,
    reference: String,
    answer: String,
    /// Why the question could not be asked.
    error: Option<String>,
    /// Right: exact match (lists as multisets of items, counts by their one number).
    exact: bool,
    /// The keyword score, 0-100.
    offline: f32,
    /// A list's items: how many of the answer's are in the reference, said, expected.
    #[serde(skip_serializing_if = "Option::is_none")]
    items: Option<[usize; 3]>,
    /// The question it follows (asked after it, in its conversation).
    #[serde(skip_serializing_if = "Option::is_none")]
    follows: Option<String>,
    /// Find level: the ids the phrase names and the ids found.
    #[serde(skip_serializing_if = "Option::is_none")]
    objects: Option<Vec<ObjectId>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    found: Option<Vec<ObjectId>>,
    grader: Option<f32>,
}

/// A question file's offline figures by level: exact match (%, the headline) and the keyword
/// score (0-100) of the questions answered in words, and the objects its `find` phrases found.
pub struct Scores {
    pub exact: Summary,
    pub keyword: Summary,
    pub find: FindTally,
    /// The questions that follow another, right against their twins spelled out.
    pub follow: FollowUps,
}

/// Follow-ups (questions asked after another in its conversation) scored beside their twins
/// (the same questions with the referent spelled out, asked on their own).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FollowUps {
    pub asked: usize,
    pub right: usize,
    /// Of the follow-ups with a twin in the file: how many, and how many of each are right.
    pub paired: usize,
    pub paired_right: usize,
    pub twins_right: usize,
}

impl FollowUps {
    fn of(follow_ups: &[(&model::vqa::Question, bool)], rows: &[Row]) -> Self {
        let mut f = FollowUps { asked: follow_ups.len(), ..Default::default() };
        for (q, exact) in follow_ups {
            f.right += *exact as usize;
            if let Some(twin) = q.spelled.as_ref().and_then(|t| rows.iter().find(|r| r.id == *t)) {
                f.paired += 1;
                f.paired_right += *exact as usize;
                f.twins_right += twin.exact as usize;
            }
        }
        f
    }

    /// `follow-ups (N): exact match X %; the same P spelled out: Y % (as follow-ups: Z %)`.
    pub fn summary(&self) -> Option<String> {
        let pct = |a: usize, b: usize| 100.0 * a as f64 / b.max(1) as f64;
        (self.asked > 0).then(|| {
            format!(
                "follow-ups ({} asked after the question they follow): exact match {:.1} %; \
                 the {} with a twin: {:.1} % as follow-ups, {:.1} % spelled out on their own",
                self.asked,
                pct(self.right, self.asked),
                self.paired,
                pct(self.paired_right, self.paired),
                pct(self.twins_right, self.paired)
            )
        })
    }
}

pub fn run(a: Args) -> anyhow::Result<()> {
    check_threshold(a.scoring.find_threshold).map_err(|e| anyhow::anyhow!("--find-threshold: {e}"))?;
    let qf = load_questions(&a.questions)?;
    // (a run that cannot be read is reported when the scene opens)
    let geometry = a.scene.geometry();
    if let Ok(state) = geometry.read_state() {
        model::question_file::check_scene(&qf, &a.questions, &state.data.dir.resolve(&geometry.dir))?;
    }
    let grader = Grader::from_env()?;
    let out = a.out.clone().unwrap_or_else(|| a.scene.language().vqa());
    let mut inputs = a.scene.own_files();
    inputs.push(("the --questions file", a.questions.clone()));
    // an earlier answers file (its first key "answers") is replaced; any other file is not
    let answers_file = |head: &[u8]| {
        let text: Vec<u8> = head.iter().copied().filter(|b| !b.is_ascii_whitespace()).collect();
        text.starts_with(b"{\"answers\"")
    };
    model::guard::output_file("--out", &out, "an answers file of vqa", answers_file, &inputs)?;
    let names = ObjectNames::of_run(&geometry, &mut Vec::new());
    score(&a.scene.open()?, (&a.questions, &qf), &out, &a.scoring, names, grader.as_ref()).map(|_| ())
}

/// Asks every question of the question file `qf` (read from `questions`) about the opened scene
/// `s`, scores the answers (offline, and with `grader` when one is set; find phrases by the
/// objects found, `names` saying which objects are searched), prints the table and writes the
/// answers to `out`; returns the offline figures per level.
pub fn score(
    s: &ChatSession,
    (questions, qf): (&Path, &QuestionFile),
    out: &Path,
    a: &Scoring,
    names: ObjectNames,
    grader: Option<&Grader>,
) -> anyhow::Result<Scores> {
    let threshold = check_threshold(a.find_threshold).map_err(|e| anyhow::anyhow!("--find-threshold: {e}"))?;
    check_find_objects(s, (questions, qf), &names)?;
    s.check_max_new_tokens("--max-new-tokens", a.max_new_tokens)?;
    let opts = model::vlm::GenerateOptions { max_new_tokens: a.max_new_tokens, ..Default::default() };
    let find = FindOptions { names, threshold };
    let bar = Progress::new("vqa", "questions");
    let total = qf.questions.len();
    let answers = model::catch_backend("answering", || {
        answer_all(s, qf, &opts, a.views, &find, |i, _, _| bar.update(i + 1, total))
    })??;
    let (mut offline, mut right, mut graded) = (Vec::new(), Vec::new(), Vec::new());
    let mut found = FindTally::default();
    let mut follow_ups = Vec::new();
    let (mut rows, mut invalid) = (Vec::new(), Vec::new());
    for (q, ans) in qf.questions.iter().zip(&answers) {
        let (text, error) = match &ans.text {
            Ok(t) => (t.clone(), None),
            Err(e) => (String::new(), Some(e.clone())),
        };
        if let Some(e) = &error {
            invalid.push(format!("{}: {e}", q.id));
        }
        let mut off = offline_score(&text, q);
        if q.level == Level::Find {
            let named = q.objects.clone().unwrap_or_default();
            let got = ans.found.clone().unwrap_or_default();
            let mut one = FindTally::default();
            one.add(&named, &got);
            found.merge(&one);
            off.exact = one.exact == 1;
            off.score = 100.0 * one.f1();
        } else if q.follows.is_some() {
            follow_ups.push((q, off.exact));
        } else {
            offline.push((q.level, off.score));
            right.push((q.level, if off.exact { 100.0 } else { 0.0 }));
        }
        let grade = match (grader, &error) {
            _ if q.level == Level::Find => None,
            (Some(g), None) => match g.grade(&q.question, &q.answer, &text) {
                Ok(v) => {
                    graded.push((q.level, v));
                    Some(v)
                }
                Err(e) => {
                    eprintln!("{}: grader: {e}", q.id);
                    None
                }
            },
            _ => None,
        };
        if a.show {
            let mark = if off.exact { "right" } else { "wrong" };
            println!("[{} {}] {} -> {:?} (reference {:?}) {mark}", q.level, q.id, q.question, text.trim(), q.answer);
        }
        rows.push(Row {
            id: q.id.clone(),
            level: q.level,
            question: q.question.clone(),
            reference: q.answer.clone(),
            answer: text,
            error,
            exact: off.exact,
            offline: off.score,
            items: off.items.map(|m| [m.matched, m.answered, m.expected]),
            follows: q.follows.clone(),
            objects: q.objects.clone(),
            found: ans.found.clone(),
            grader: grade,
        });
    }
    let follow = FollowUps::of(&follow_ups, &rows);
    let scores = Scores { exact: summarize(&right), keyword: summarize(&offline), find: found, follow };
    println!("| scorer | view | object | scene | overall | questions |\n|---|---|---|---|---|---|");
    println!("{}", table_row("exact match (%)", &scores.exact));
    println!("{}", table_row("keyword score (0-100)", &scores.keyword));
    if found.phrases > 0 {
        println!("{} (threshold {threshold})", found.summary());
    }
    if let Some(line) = scores.follow.summary() {
        println!("{line}");
    }
    if !graded.is_empty() {
        let name = grader.map(|g| g.model.as_str()).unwrap_or("");
        println!("{}", table_row(&format!("grader {name} (0-100)"), &summarize(&graded)));
    } else if grader.is_none() {
        eprintln!(
            "(no grader: set CHATSPLAT_GRADER_URL, CHATSPLAT_GRADER_MODEL and CHATSPLAT_GRADER_KEY for \
                GPT-4o-style 0-100 grades)"
        );
    }
    let json = serde_json::json!({"questions": questions.display().to_string(), "answers": rows});
    model::io::write_json(out, &json)?;
    println!("answers -> {}", out.display());
    if !invalid.is_empty() && !a.keep_going {
        anyhow::bail!(
            "{}: {} question(s) could not be asked (scored 0; --keep-going accepts this): {}",
            questions.display(),
            invalid.len(),
            invalid.join("; ")
        );
    }
    if !invalid.is_empty() {
        eprintln!("warning: {} question(s) could not be asked (scored 0): {}", invalid.len(), invalid.join("; "));
    }
    Ok(scores)
}

/// The objects a question file's `find` entries name (`qf`, read from `path`) are the scene's:
/// one a synthetic scene lists (its table is never searched: `names`), else one held by some
/// Gaussian of `s`;
/// else the file is refused, naming the question and the object, before anything is asked.
fn check_find_objects(s: &ChatSession, (path, qf): (&Path, &QuestionFile), names: &ObjectNames) -> anyhow::Result<()> {
    let finds: Vec<(usize, &model::vqa::Question)> =
        qf.questions.iter().enumerate().filter(|(_, q)| q.level == Level::Find).collect();
    if finds.is_empty() {
        return Ok(());
    }
    let held: std::collections::BTreeSet<ObjectId> = s.scene.splats.gaussian_classes().into_iter().collect();
    for (i, q) in finds {
        for &id in q.objects.iter().flatten() {
            // a synthetic scene lists its objects (its table is ground, never searched); any other
            // scene has the objects its Gaussians hold
            let why = match names.lists(id) {
                Some(true) => continue,
                Some(false) if names.name(id) == "table" => {
                    format!("object {id}, the table, which find never searches")
                }
                None if names.surface(id) => {
                    format!("object {id}, a surface (the ground or a table, masks.json), which find never searches")
                }
                None if held.contains(&id) => continue,
                _ => format!("object {id}, which the scene does not have"),
            };
            anyhow::bail!("{}: question {i} (id {:?}): \"objects\" names {why}", path.display(), q.id);
        }
    }
    Ok(())
}

/// `| name | view | object | scene | overall | questions |` of a summary.
fn table_row(name: &str, s: &Summary) -> String {
    let fmt = |x: Option<f32>| x.map(|v| format!("{v:.1}")).unwrap_or_else(|| "-".into());
    let means = [s.view.mean, s.object.mean, s.scene.mean, s.overall.mean].map(fmt);
    format!("| {name} | {} | {} |", means.join(" | "), s.overall.count)
}
