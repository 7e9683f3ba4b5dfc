//! Questions with reference answers about a synthetic scene, in the `chatsplat vqa` format.

use super::scene::Primitive;

/// "red ball" -> "ball".
fn noun(name: &str) -> &str {
    name.split_whitespace().last().unwrap_or(name)
}

/// Questions with reference answers about the scene (the `chatsplat vqa` format).
pub fn questions(objects: &[Primitive], best: &[(usize, usize, [usize; 2])]) -> serde_json::Value {
    let mut qs = vec![
        serde_json::json!({"id": "view-count", "level": "view", "view": 0,
            "question": "How many objects are on the table?",
            "answer": format!("{}", objects.len()), "keywords": [format!("{}", objects.len())]}),
        serde_json::json!({"id": "scene-objects", "level": "scene", "question": "List the objects on the table.",
            "answer": objects.iter().map(|o| o.name).collect::<Vec<_>>().join(", "),
            "keywords": objects.iter().map(|o| noun(o.name)).collect::<Vec<_>>()}),
    ];
    for (k, (o, &(pixels, view, [x, y]))) in objects.iter().zip(best).enumerate() {
        if pixels == 0 {
            continue;
        }
        let colour = o.name.split_whitespace().next().unwrap_or("");
        qs.push(
            serde_json::json!({"id": format!("object-{k}-what"), "level": "object", "view": view, "object": [x, y],
            "question": "What is this object?", "answer": o.name, "keywords": [noun(o.name)]}),
        );
        qs.push(
            serde_json::json!({"id": format!("object-{k}-colour"), "level": "object", "view": view, "object": [x, y],
            "question": "What colour is this object?", "answer": colour, "keywords": [colour]}),
        );
    }
    serde_json::json!({"scene": "chatsplat synthetic tabletop", "questions": qs})
}
