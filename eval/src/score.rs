//! Scoring answers to annotated questions about a scene (the paper's view / object / scene-level
//! question answering; the question files are `model::vqa`), two ways: an offline string scorer
//! that needs nothing, and an OpenAI-compatible LLM grader (the paper grades with GPT-4o on a
//! 0-100 rubric).

use model::vqa::Level;

const NUMBERS: &str = "zero one two three four five six seven eight nine ten eleven twelve \
    thirteen fourteen fifteen sixteen seventeen eighteen nineteen twenty";
/// Function words ignored when a reference's content words stand in for keywords.
const STOPWORDS: &str = "is are was were be of in on at to and or it its this that there with for by has have as from";

/// Lowercases, drops apostrophes, turns other punctuation into spaces (keeping a decimal point
/// between digits), drops the articles a/an/the, maps zero..twenty to digits and collapses
/// whitespace.
pub fn normalize(s: &str) -> String {
    let chars: Vec<char> = s.chars().collect();
    let mut out = String::with_capacity(s.len());
    for (i, &c) in chars.iter().enumerate() {
        let digit_at = |j: Option<usize>| j.and_then(|j| chars.get(j)).is_some_and(|c| c.is_ascii_digit());
        if c.is_alphanumeric() {
            out.extend(c.to_lowercase());
        } else if c == '\'' || c == '\u{2019}' {
        } else if c == '.' && digit_at(i.checked_sub(1)) && digit_at(Some(i + 1)) {
            out.push('.');
        } else {
            out.push(' ');
        }
    }
    let words: Vec<String> = out
        .split_whitespace()
        .filter(|w| !matches!(*w, "a" | "an" | "the"))
        .map(|w| match NUMBERS.split_whitespace().position(|n| n == w) {
            Some(k) => k.to_string(),
            None => w.to_string(),
        })
        .collect();
    words.join(" ")
}

/// Whether `needle` (non-empty) occurs as a contiguous run of whole words in `hay`.
fn contains_phrase(hay: &[&str], needle: &[&str]) -> bool {
    !needle.is_empty() && hay.windows(needle.len()).any(|w| w == needle)
}

/// The offline score of one answer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OfflineScore {
    /// Normalized answer equals normalized reference.
    pub exact: bool,
    /// Fraction of keywords found as whole words (0-1).
    pub keyword_recall: f32,
    /// 0-100.
    pub score: f32,
}

/// Scores `answer` against `reference`: 100 when the normalized texts are equal or the normalized
/// reference occurs as a whole-word phrase in the answer, else 100 × keyword recall. Keywords are
/// normalized and matched as whole-word phrases; without keywords the reference's content words
/// (minus a few function words) are used. A plain string scorer: "not red" still contains "red".
pub fn offline_score(answer: &str, reference: &str, keywords: &[String]) -> OfflineScore {
    let (ans, refn) = (normalize(answer), normalize(reference));
    let ans_w: Vec<&str> = ans.split_whitespace().collect();
    let ref_w: Vec<&str> = refn.split_whitespace().collect();
    let exact = ans == refn;
    let mut keys: Vec<String> = keywords.iter().map(|k| normalize(k)).filter(|k| !k.is_empty()).collect();
    if keys.is_empty() {
        for w in ref_w.iter().filter(|w| !STOPWORDS.split_whitespace().any(|s| s == **w)) {
            if !keys.iter().any(|k| k == w) {
                keys.push(w.to_string());
            }
        }
        if keys.is_empty() {
            keys = ref_w.iter().map(|w| w.to_string()).collect();
        }
    }
    let hits = keys.iter().filter(|k| contains_phrase(&ans_w, &k.split_whitespace().collect::<Vec<_>>())).count();
    let keyword_recall = if keys.is_empty() { 0.0 } else { hits as f32 / keys.len() as f32 };
    let score = if exact || contains_phrase(&ans_w, &ref_w) { 100.0 } else { 100.0 * keyword_recall };
    OfflineScore { exact, keyword_recall, score }
}

/// Extracts the grade from a grader reply: the first number in it, skipping a rubric range echoed
/// as "0-100" / "0 to 100". Returns `None` when there is no number, or when the first number is
/// negative or above 100 (out of the rubric: rejected, not clamped). A decimal part is kept.
pub fn parse_score(text: &str) -> Option<f32> {
    let c: Vec<char> = text.chars().collect();
    let mut i = 0;
    let mut skip_next = false;
    while i < c.len() {
        if !c[i].is_ascii_digit() {
            i += 1;
            continue;
        }
        let start = i;
        while i < c.len() && c[i].is_ascii_digit() {
            i += 1;
        }
        if i + 1 < c.len() && c[i] == '.' && c[i + 1].is_ascii_digit() {
            i += 1;
            while i < c.len() && c[i].is_ascii_digit() {
                i += 1;
            }
        }
        let num: String = c[start..i].iter().collect();
        if std::mem::take(&mut skip_next) {
            continue; // the upper end of a range
        }
        let mut j = i;
        while j < c.len() && c[j] == ' ' {
            j += 1;
        }
        let rest: String = c[j..c.len().min(j + 3)].iter().collect();
        if rest.starts_with(['-', '\u{2013}']) || rest.starts_with("to ") {
            let after = c[j..].iter().skip_while(|ch| !ch.is_ascii_digit()).count();
            if after > 0 && c[j..c.len() - after].iter().all(|ch| " -\u{2013}to".contains(*ch)) {
                skip_next = true;
                continue; // the lower end of a range
            }
        }
        let negative = start > 0 && c[start - 1] == '-';
        let v: f32 = num.parse().ok()?;
        return (!negative && v <= 100.0).then_some(v);
    }
    None
}

const ENV_URL: &str = "CHATSPLAT_GRADER_URL";
const ENV_MODEL: &str = "CHATSPLAT_GRADER_MODEL";
const ENV_KEY: &str = "CHATSPLAT_GRADER_KEY";

/// Why grading failed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum GraderError {
    /// The grader URL is set but not the model or the key.
    #[error("{ENV_URL} is set but {0} is not")]
    MissingEnv(&'static str),
    /// The request failed or the endpoint refused it (the key is redacted from every field).
    #[error("grader request to {endpoint} failed ({status}): {detail}; response: {response}")]
    Request { endpoint: String, status: String, detail: String, response: String },
    #[error("grader returned a non-JSON response ({error}): {body}")]
    NotJson { error: String, body: String },
    #[error("grader response has no choices[0].message.content: {0}")]
    NoContent(String),
    #[error("no score 0-100 in grader reply: {0:?}")]
    NoScore(String),
}

/// An OpenAI-compatible chat-completions grader, asked over HTTP(S) in process (ureq, rustls).
#[derive(Clone, PartialEq)]
pub struct Grader {
    /// Base URL without the trailing slash, e.g. `https://api.openai.com/v1`.
    pub url: String,
    pub model: String,
    pub key: String,
}

impl std::fmt::Debug for Grader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Grader").field("url", &self.url).field("model", &self.model).field("key", &"***").finish()
    }
}

fn truncate(s: &str, n: usize) -> String {
    let s = s.trim();
    if s.chars().count() <= n { s.to_string() } else { s.chars().take(n).collect::<String>() + "…" }
}

impl Grader {
    /// Reads `CHATSPLAT_GRADER_URL`, `CHATSPLAT_GRADER_MODEL` and `CHATSPLAT_GRADER_KEY`.
    /// `Ok(None)` when the URL is unset or empty; an error naming the variable when the URL is set
    /// but the model or key is missing.
    pub fn from_env() -> Result<Option<Grader>, GraderError> {
        let var = |n: &str| std::env::var(n).ok().map(|v| v.trim().to_string()).filter(|v| !v.is_empty());
        let Some(url) = var(ENV_URL) else { return Ok(None) };
        let model = var(ENV_MODEL).ok_or(GraderError::MissingEnv(ENV_MODEL))?;
        let key = var(ENV_KEY).ok_or(GraderError::MissingEnv(ENV_KEY))?;
        Ok(Some(Grader { url: url.trim_end_matches('/').to_string(), model, key }))
    }

    /// The rubric sent as the user message.
    pub fn prompt(question: &str, reference: &str, answer: &str) -> String {
        format!(
            "You are grading an answer to a question about a 3D scene.\n\
             Compare the candidate answer with the reference answer and judge its correctness and \
             completeness: 100 means fully correct and complete, 0 means wrong or unrelated; give \
             partial credit for partially correct or incomplete answers. Extra detail is fine \
             unless it contradicts the reference.\n\n\
             Question: {question}\nReference answer: {reference}\nCandidate answer: {answer}\n\n\
             Reply with only one integer from 0 to 100 and nothing else."
        )
    }

    /// The `chat/completions` request body (temperature 0).
    pub fn request_body(&self, question: &str, reference: &str, answer: &str) -> serde_json::Value {
        serde_json::json!({
            "model": self.model,
            "temperature": 0,
            "messages": [
                {"role": "system", "content": "You are a strict, consistent grader. You reply with a single integer."},
                {"role": "user", "content": Self::prompt(question, reference, answer)},
            ],
        })
    }

    /// Extracts the score from a chat-completions response body.
    pub fn parse_response(body: &str) -> Result<f32, GraderError> {
        let v: serde_json::Value = serde_json::from_str(body)
            .map_err(|e| GraderError::NotJson { error: e.to_string(), body: truncate(body, 300) })?;
        let content = v["choices"][0]["message"]["content"]
            .as_str()
            .ok_or_else(|| GraderError::NoContent(truncate(body, 300)))?;
        parse_score(content).ok_or_else(|| GraderError::NoScore(truncate(content, 300)))
    }

    /// Grades one answer with a POST to `{url}/chat/completions`, in process: the key travels in
    /// the request's `Authorization` header only (no other process sees it in its arguments, as
    /// one did when this spawned `curl`) and is redacted from every error.
    pub fn grade(&self, question: &str, reference: &str, answer: &str) -> Result<f32, GraderError> {
        let endpoint = format!("{}/chat/completions", self.url);
        let body = self.request_body(question, reference, answer).to_string();
        let redact = |s: &str| if self.key.is_empty() { s.to_string() } else { s.replace(&self.key, "***") };
        let failed = |status: String, detail: String, response: &str| GraderError::Request {
            endpoint: redact(&endpoint),
            status,
            detail: redact(&detail),
            response: truncate(&redact(response), 300),
        };
        let agent: ureq::Agent = ureq::Agent::config_builder()
            .timeout_global(Some(std::time::Duration::from_secs(120)))
            .http_status_as_error(false)
            .build()
            .into();
        let mut response = agent
            .post(&endpoint)
            .header("Authorization", &format!("Bearer {}", self.key))
            .header("Content-Type", "application/json")
            .send(body.as_bytes())
            .map_err(|e| failed("no response".into(), e.to_string(), ""))?;
        let status = response.status();
        let text = response.body_mut().read_to_string().map_err(|e| failed(status.to_string(), e.to_string(), ""))?;
        if !status.is_success() {
            return Err(failed(status.to_string(), "the endpoint refused the request".into(), &text));
        }
        Self::parse_response(&redact(&text))
    }
}

/// Count and mean score (None when there are no scores) of one group.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LevelSummary {
    pub count: usize,
    pub mean: Option<f32>,
}

/// Mean scores per level and overall (the mean over all questions, not over levels).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Summary {
    pub view: LevelSummary,
    pub object: LevelSummary,
    pub scene: LevelSummary,
    pub overall: LevelSummary,
}

impl Summary {
    pub fn level(&self, level: Level) -> LevelSummary {
        match level {
            Level::View => self.view,
            Level::Object => self.object,
            Level::Scene => self.scene,
        }
    }
}

pub fn summarize(scores: &[(Level, f32)]) -> Summary {
    let group = |keep: &dyn Fn(Level) -> bool| {
        let v: Vec<f64> = scores.iter().filter(|(l, _)| keep(*l)).map(|&(_, s)| s as f64).collect();
        let mean = (!v.is_empty()).then(|| (v.iter().sum::<f64>() / v.len() as f64) as f32);
        LevelSummary { count: v.len(), mean }
    };
    Summary {
        view: group(&|l| l == Level::View),
        object: group(&|l| l == Level::Object),
        scene: group(&|l| l == Level::Scene),
        overall: group(&|_| true),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kw(k: &[&str]) -> Vec<String> {
        k.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn normalization() {
        assert_eq!(normalize("  The RED, cube!  "), "red cube");
        assert_eq!(normalize("There are Three chairs and an apple."), "there are 3 chairs and apple");
        assert_eq!(normalize("It's twenty-one"), "its 20 1");
        assert_eq!(normalize("about 3.5 m. Then"), "about 3.5 m then");
        assert_eq!(normalize("theatre a"), "theatre");
        assert_eq!(normalize("?!"), "");
    }

    #[test]
    fn offline_scoring() {
        let s = offline_score("Red.", "red", &[]);
        assert!(s.exact && s.score == 100.0);
        let s = offline_score("The cube is red.", "red", &[]);
        assert!(!s.exact && s.score == 100.0);
        assert_eq!(offline_score("blue", "red", &[]).score, 0.0);
        assert_eq!(offline_score("reddish", "red", &[]).score, 0.0, "whole words only");
        assert_eq!(offline_score("3", "three", &[]).score, 100.0);
        let s = offline_score("a red sphere", "red cube", &kw(&["Red", "cube"]));
        assert_eq!((s.keyword_recall, s.score), (0.5, 50.0));
        // No keywords: the reference's content words ("wooden", "chair"; "is" is a stopword).
        let s = offline_score("it looks wooden", "is a wooden chair", &[]);
        assert_eq!((s.keyword_recall, s.score), (0.5, 50.0));
        let s = offline_score("a dark red table", "dark red", &kw(&["dark red", "table"]));
        assert_eq!((s.keyword_recall, s.score), (1.0, 100.0));
        assert_eq!(offline_score("", "red", &[]).score, 0.0);
    }

    #[test]
    fn score_parsing() {
        assert_eq!(parse_score("85"), Some(85.0));
        assert_eq!(parse_score("Score: 85"), Some(85.0));
        assert_eq!(parse_score("85/100"), Some(85.0));
        assert_eq!(parse_score("0"), Some(0.0));
        assert_eq!(parse_score("100."), Some(100.0));
        assert_eq!(parse_score("72.5"), Some(72.5));
        assert_eq!(parse_score("Score (0-100): 40"), Some(40.0));
        assert_eq!(parse_score("on a scale of 0 to 100, 90"), Some(90.0));
        assert_eq!(parse_score("I'd give it 101"), None, "out of range is rejected, not clamped");
        assert_eq!(parse_score("-5"), None);
        assert_eq!(parse_score("none"), None);
        assert_eq!(parse_score(""), None);
    }

    #[test]
    fn request_body_and_response() {
        let g = Grader { url: "http://x/v1".into(), model: "gpt-4o".into(), key: "sk-secret".into() };
        let b = g.request_body("What colour?", "red", "blue");
        assert_eq!(b["model"], "gpt-4o");
        assert_eq!(b["temperature"], 0);
        let msgs = b["messages"].as_array().unwrap();
        assert_eq!(msgs.last().unwrap()["role"], "user");
        let user = msgs.last().unwrap()["content"].as_str().unwrap();
        assert!(user.contains("What colour?") && user.contains("red") && user.contains("blue"));
        assert!(user.contains("0 to 100"));
        assert!(!b.to_string().contains("sk-secret"));
        assert!(!format!("{g:?}").contains("sk-secret"));

        let ok = r#"{"choices": [{"message": {"role": "assistant", "content": "Score: 85"}}]}"#;
        assert_eq!(Grader::parse_response(ok), Ok(85.0));
        let none = r#"{"choices": [{"message": {"content": "cannot judge"}}]}"#;
        assert!(Grader::parse_response(none).unwrap_err().to_string().contains("no score"));
        let e = Grader::parse_response(&format!("<html>{}</html>", "x".repeat(1000))).unwrap_err().to_string();
        assert!(e.contains("non-JSON") && e.chars().count() < 450, "{e}");
        assert!(Grader::parse_response(r#"{"error": "bad"}"#).unwrap_err().to_string().contains("choices[0]"));
    }

    /// A local endpoint: the request arrives with the key in its header, a reply is scored, and
    /// an error reply that echoes the key never shows it.
    #[test]
    fn grade_asks_over_http_with_the_key_in_the_header_only() {
        use std::io::{BufRead, BufReader, Read, Write};
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let replies = [
            ("200 OK", r#"{"choices": [{"message": {"content": "85"}}]}"#.to_string()),
            ("401 Unauthorized", r#"{"error": "invalid key sk-secret-123"}"#.to_string()),
        ];
        let server = std::thread::spawn(move || {
            let mut requests = Vec::new();
            for (status, body) in replies {
                let (stream, _) = listener.accept().unwrap();
                let mut r = BufReader::new(stream);
                let (mut head, mut len) = (String::new(), 0);
                loop {
                    let mut line = String::new();
                    r.read_line(&mut line).unwrap();
                    if let Some(v) = line.to_ascii_lowercase().strip_prefix("content-length:") {
                        len = v.trim().parse().unwrap();
                    }
                    head.push_str(&line);
                    if line == "\r\n" {
                        break;
                    }
                }
                let mut body_in = vec![0; len];
                r.read_exact(&mut body_in).unwrap();
                requests.push((head, String::from_utf8(body_in).unwrap()));
                let fields = "Content-Type: application/json\r\nConnection: close";
                let reply = format!("HTTP/1.1 {status}\r\n{fields}\r\nContent-Length: {}\r\n\r\n{body}", body.len());
                r.get_mut().write_all(reply.as_bytes()).unwrap();
            }
            requests
        });
        let g = Grader { url: format!("http://{addr}/v1"), model: "judge".into(), key: "sk-secret-123".into() };
        assert_eq!(g.grade("What colour?", "red", "red"), Ok(85.0));
        let e = g.grade("What colour?", "red", "blue").unwrap_err().to_string();
        assert!(e.contains("401") && e.contains("***") && !e.contains("sk-secret-123"), "{e}");
        let requests = server.join().unwrap();
        let (head, body) = &requests[0];
        assert!(head.starts_with("POST /v1/chat/completions "), "{head}");
        assert!(head.to_ascii_lowercase().contains("authorization: bearer sk-secret-123"), "{head}");
        assert!(body.contains("\"model\":\"judge\"") && !body.contains("sk-secret-123"), "{body}");
        // nothing listens there any more: a failed connection names the endpoint, not the key
        let e = g.grade("q", "r", "a").unwrap_err().to_string();
        assert!(e.contains("no response") && e.contains(&addr.to_string()) && !e.contains("sk-secret-123"), "{e}");
    }

    /// The only test touching the process environment (tests run in parallel threads).
    #[test]
    fn grader_from_env() {
        // SAFETY: no other test reads or writes the environment (this is the only one), and the
        // grader reads it only inside this test's own calls.
        let set = |k: &str, v: Option<&str>| unsafe {
            match v {
                Some(v) => std::env::set_var(k, v),
                None => std::env::remove_var(k),
            }
        };
        set(ENV_URL, None);
        set(ENV_MODEL, Some("gpt-4o"));
        assert_eq!(Grader::from_env(), Ok(None));
        set(ENV_URL, Some("https://api.example.com/v1/"));
        set(ENV_KEY, None);
        let e = Grader::from_env().unwrap_err().to_string();
        assert!(e.contains(ENV_KEY), "{e}");
        set(ENV_MODEL, None);
        set(ENV_KEY, Some("sk-secret"));
        assert!(Grader::from_env().unwrap_err().to_string().contains(ENV_MODEL));
        set(ENV_MODEL, Some("gpt-4o"));
        let g = Grader::from_env().unwrap().unwrap();
        assert_eq!(
            (g.url.as_str(), g.model.as_str(), g.key.as_str()),
            ("https://api.example.com/v1", "gpt-4o", "sk-secret")
        );
        for k in [ENV_URL, ENV_MODEL, ENV_KEY] {
            set(k, None);
        }
    }

    #[test]
    fn summaries() {
        use Level::*;
        let s = summarize(&[(View, 100.0), (View, 50.0), (Scene, 0.0), (View, 0.0)]);
        assert_eq!(s.view, LevelSummary { count: 3, mean: Some(50.0) });
        assert_eq!(s.object, LevelSummary { count: 0, mean: None });
        assert_eq!(s.level(Scene), LevelSummary { count: 1, mean: Some(0.0) });
        assert_eq!(s.overall, LevelSummary { count: 4, mean: Some(37.5) });
        assert_eq!(summarize(&[]).overall, LevelSummary::default());
    }
}
