//! The question forms of the synthetic tabletops ([`super::questions`]): what a model trained on
//! them (the built-in model, any `chatsplat train-vlm` model) knows how to answer. A form is a
//! question with slots for the words that change; [`form_of`] tells whether a question a user
//! typed is one of them, so that a question far from every form is marked instead of answered
//! with a bare colour.

use super::scene::{Color, Shape};
use crate::question_file::Level;

/// A question form: the level it is asked at and its words, with the slots `{color}` (a colour
/// word), `{shape}` (a shape word), `{shapes}` (its plural) and `{name}` (a colour and a shape).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Form {
    pub level: Level,
    pub text: &'static str,
}

const fn form(level: Level, text: &'static str) -> Form {
    Form { level, text }
}

/// Every form the synthetic scenes' questions and follow-ups take, by level (the question
/// generator's own: a test holds every generated question to one of them).
pub const FORMS: &[Form] = &[
    form(Level::View, "What objects are there?"),
    form(Level::View, "How many objects are there?"),
    form(Level::View, "What colors are there?"),
    form(Level::View, "What shapes are there?"),
    form(Level::View, "What color is the {shape}?"),
    form(Level::View, "What shape is the {color} object?"),
    form(Level::View, "Is there a {name}?"),
    form(Level::View, "Is the {name} left of the {name}?"),
    form(Level::View, "Which object is nearest?"),
    form(Level::View, "Is it left of the {name}?"),
    form(Level::Object, "What is this?"),
    form(Level::Object, "What color is this?"),
    form(Level::Object, "What shape is this?"),
    form(Level::Object, "What size is this?"),
    form(Level::Object, "What color is it?"),
    form(Level::Object, "What shape is it?"),
    form(Level::Object, "What size is it?"),
    form(Level::Scene, "What objects are in the scene?"),
    form(Level::Scene, "How many objects are in the scene?"),
    form(Level::Scene, "How many {color} objects are in the scene?"),
    form(Level::Scene, "How many {shapes} are in the scene?"),
];

/// The words of `text`, lower case, without punctuation.
fn words(text: &str) -> Vec<String> {
    text.split(|c: char| c.is_whitespace() || matches!(c, '?' | '.' | '!' | ','))
        .filter(|w| !w.is_empty())
        .map(str::to_lowercase)
        .collect()
}

fn is_color(w: &str) -> bool {
    Color::ALL.iter().any(|c| c.word() == w)
}

fn is_shape(w: &str) -> bool {
    Shape::ALL.iter().any(|s| s.word() == w)
}

impl Form {
    /// Whether `question` is this form with its slots filled (case, spacing and the question
    /// mark aside).
    pub fn matches(&self, question: &str) -> bool {
        let (pattern, q) = (words(self.text), words(question));
        let mut k = 0;
        for p in &pattern {
            let ok = match p.as_str() {
                "{color}" => q.get(k).is_some_and(|w| is_color(w)),
                "{shape}" => q.get(k).is_some_and(|w| is_shape(w)),
                "{shapes}" => q.get(k).is_some_and(|w| Shape::ALL.iter().any(|s| s.plural() == w)),
                "{name}" => {
                    let name = q.get(k).is_some_and(|w| is_color(w)) && q.get(k + 1).is_some_and(|w| is_shape(w));
                    k += name as usize;
                    name
                }
                word => q.get(k).is_some_and(|w| w == word),
            };
            if !ok {
                return false;
            }
            k += 1;
        }
        k == q.len()
    }

    /// The form with its slots filled from an object's `color` and `shape` (a second `{name}`:
    /// `other`'s), as an example a user can ask.
    pub fn example(&self, color: Color, shape: Shape, other: (Color, Shape)) -> String {
        let name = format!("{} {}", color.word(), shape.word());
        let mut text = self.text.replacen("{name}", &name, 1);
        text = text.replace("{name}", &format!("{} {}", other.0.word(), other.1.word()));
        text.replace("{color}", color.word()).replace("{shapes}", shape.plural()).replace("{shape}", shape.word())
    }
}

/// A list answer's items: "red cube blue cone" -> "red cube", "blue cone"; "red blue" -> "red",
/// "blue" (and shape lists alike); `None` for an answer of one item or of other words.
pub fn list_items(answer: &str) -> Option<Vec<String>> {
    let w = words(answer);
    let names = w.len() >= 4 && w.len().is_multiple_of(2) && w.chunks(2).all(|p| is_color(&p[0]) && is_shape(&p[1]));
    if names {
        return Some(w.chunks(2).map(|p| p.join(" ")).collect());
    }
    let one_sort = w.len() >= 2 && (w.iter().all(|x| is_color(x)) || w.iter().all(|x| is_shape(x)));
    one_sort.then_some(w)
}

/// The form `question` takes at `level`, if it takes one.
pub fn form_of(level: Level, question: &str) -> Option<&'static Form> {
    FORMS.iter().find(|f| f.level == level && f.matches(question))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn forms_match_their_questions_and_nothing_else() {
        assert!(form_of(Level::View, "what color is the cone").is_some());
        assert!(form_of(Level::View, "Is the red cube left of the blue cone?").is_some());
        assert!(form_of(Level::Scene, "How many tori are in the scene?").is_some());
        assert!(form_of(Level::View, "What is on the table?").is_none());
        assert!(form_of(Level::View, "What color is the table?").is_none());
        assert!(form_of(Level::View, "Is there a red?").is_none());
        assert!(form_of(Level::View, "What objects are there? And why?").is_none());
        // the level counts: an object question asked of a view is not a view form
        assert!(form_of(Level::Object, "What objects are there?").is_none());
        assert!(form_of(Level::View, "What is this?").is_none());
    }

    #[test]
    fn list_answers_split_into_their_items() {
        assert_eq!(list_items("red cube blue cone").unwrap(), ["red cube", "blue cone"]);
        assert_eq!(list_items("red blue").unwrap(), ["red", "blue"]);
        assert_eq!(list_items("cube torus").unwrap(), ["cube", "torus"]);
        assert_eq!(list_items("red cube"), None);
        assert_eq!(list_items("red cube blue"), None);
        assert_eq!(list_items("yes"), None);
        assert_eq!(list_items("3"), None);
    }

    #[test]
    fn examples_fill_every_slot_and_match_their_form() {
        for f in FORMS {
            let e = f.example(Color::Red, Shape::Torus, (Color::Blue, Shape::Cube));
            assert!(!e.contains('{'), "{e}");
            assert!(f.matches(&e), "{e} does not match {}", f.text);
        }
    }
}
