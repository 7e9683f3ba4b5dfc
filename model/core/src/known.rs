//! What a model knows how to be asked. A model `chatsplat train-vlm` trained (the built-in one
//! among them: its `train_config.json` beside the weights) learned the synthetic tabletops'
//! question forms and nothing else: asked "What is on the table?" it answers with a bare colour.
//! Here the forms it offers, filled with the scene's own objects ([`examples`]), and a note for a
//! question that takes none of them ([`unknown_question_note`]). A LLaVA-OneVision from Hugging
//! Face takes any question: no forms, no notes.

use crate::chat::Target;
use crate::data::synth::forms::{FORMS, Form, form_of};
use crate::data::synth::scene::{Color, Shape};
use crate::question_file::Level;
use crate::vlm::LlavaOnevision;

/// The question forms `vlm` was trained on, or `None` for a model that takes any question.
pub fn forms(vlm: &LlavaOnevision) -> Option<&'static [Form]> {
    vlm.dir.join("train_config.json").is_file().then_some(FORMS)
}

/// The level a question about `target` is asked at.
pub fn level_of(target: &Target) -> Level {
    match target {
        Target::View(_) => Level::View,
        Target::Object(_) => Level::Object,
        Target::Scene(_) => Level::Scene,
    }
}

/// A note for `question` asked of `target` when `vlm` was trained on question forms and the
/// question takes none of them at that level: its answer is a guess. `None` otherwise.
pub fn unknown_question_note(vlm: &LlavaOnevision, target: &Target, question: &str) -> Option<String> {
    forms(vlm)?;
    let level = level_of(target);
    form_of(level, question).is_none().then(|| {
        let some: Vec<String> =
            FORMS.iter().filter(|f| f.level == level).take(3).map(|f| format!("\"{}\"", f.text)).collect();
        format!(
            "\"{}\" is not a question this model was trained on, so its answer is a guess: at {level} level it knows \
             questions such as {}",
            question.trim(),
            some.join(", ")
        )
    })
}

/// The colour and shape a name such as "red cone" gives, if it gives both.
fn color_shape(name: &str) -> Option<(Color, Shape)> {
    let mut words = name.split_whitespace();
    let (c, s) = (words.next()?, words.next()?);
    Some((Color::ALL.into_iter().find(|x| x.word() == c)?, Shape::ALL.into_iter().find(|x| x.word() == s)?))
}

/// Every form `vlm` was trained on, by level, as a question about this scene: its slots filled
/// with the first two `objects` named by a colour and a shape (a red cube and a blue cone where
/// the scene has none). `None` for a model that takes any question.
pub fn examples(vlm: &LlavaOnevision, objects: &[String]) -> Option<Vec<(Level, String)>> {
    let forms = forms(vlm)?;
    let mut named = objects.iter().filter_map(|n| color_shape(n));
    let first = named.next().unwrap_or((Color::Red, Shape::Cube));
    let second = named.next().unwrap_or(if first == (Color::Blue, Shape::Cone) {
        (Color::Red, Shape::Cube)
    } else {
        (Color::Blue, Shape::Cone)
    });
    Some(forms.iter().map(|f| (f.level, f.example(first.0, first.1, second))).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_give_their_colour_and_shape() {
        assert_eq!(color_shape("red cone"), Some((Color::Red, Shape::Cone)));
        assert_eq!(color_shape("object 4"), None);
        assert_eq!(color_shape("red"), None);
    }
}
