//! The conversations the server keeps: each has an id the first answer hands out, the scope it
//! is about, and the model-side [`Conversation`] (its turns and their keys and values). The
//! latest [`KEPT`] are kept; a question naming another is refused, and so is one whose scope is
//! not its conversation's (a moved camera or another object is a new conversation).

use crate::error::ApiError;
use crate::scene_info::ObjectNames;
use axum::http::StatusCode;
use model::ObjectId;
use model::chat::Conversation;
use splat_kernels::Camera;
use std::collections::HashMap;

/// What a question is about, validated but not yet resolved against the scene.
#[derive(Clone, Debug, PartialEq)]
pub enum Scope {
    /// The view from this camera.
    View(Camera),
    /// Object `id` as seen from this camera (where it was picked or followed to).
    Object { camera: Camera, id: ObjectId },
    /// The whole scene through this many views spread around it.
    Scene { views: usize },
}

/// Conversations kept (the latest used); an older one is forgotten.
pub const KEPT: usize = 16;

struct Kept {
    scope: Scope,
    /// `None` while one of its questions is being answered.
    conversation: Option<Conversation>,
    used: u64,
}

/// The server's conversations.
#[derive(Default)]
pub struct Conversations {
    kept: HashMap<u64, Kept>,
    last_id: u64,
    clock: u64,
}

impl Conversations {
    /// Checks that conversation `id` is kept and about `scope`.
    pub fn check(&self, id: u64, scope: &Scope, names: &ObjectNames) -> Result<(), ApiError> {
        let kept = self.kept.get(&id).ok_or_else(|| {
            let message = format!(
                "no conversation {id}: it was never started here or is forgotten (the server keeps the latest \
                 {KEPT}); leave `conversation` out to start a new one"
            );
            ApiError { status: StatusCode::NOT_FOUND, field: Some("conversation".into()), message }
        })?;
        if kept.scope != *scope {
            let message = format!(
                "conversation {id} is about {}, and this question about {}: a new target is a new conversation \
                 (leave `conversation` out)",
                describe(&kept.scope, names, "the camera it began at"),
                describe(scope, names, "another camera")
            );
            return Err(ApiError { status: StatusCode::CONFLICT, field: Some("conversation".into()), message });
        }
        Ok(())
    }

    /// A new conversation's id, reserved for `scope` (its conversation comes back by
    /// [`put_back`](Self::put_back)).
    pub fn start(&mut self, scope: &Scope) -> u64 {
        self.last_id += 1;
        self.clock += 1;
        self.kept.insert(self.last_id, Kept { scope: scope.clone(), conversation: None, used: self.clock });
        self.last_id
    }

    /// Takes conversation `id` out to answer a question about `scope` in it.
    pub fn take(&mut self, id: u64, scope: &Scope, names: &ObjectNames) -> Result<Conversation, ApiError> {
        self.check(id, scope, names)?;
        self.clock += 1;
        let kept = self.kept.get_mut(&id).expect("checked");
        kept.used = self.clock;
        kept.conversation.take().ok_or_else(|| {
            ApiError::status(StatusCode::CONFLICT, format!("conversation {id} is answering another question"))
        })
    }

    /// Keeps `conversation` as `id` again, forgetting the least recently used beyond [`KEPT`].
    pub fn put_back(&mut self, id: u64, conversation: Conversation) {
        if let Some(kept) = self.kept.get_mut(&id) {
            kept.conversation = Some(conversation);
        }
        while self.kept.len() > KEPT {
            let idle = self.kept.iter().filter(|(_, k)| k.conversation.is_some());
            let Some(oldest) = idle.min_by_key(|(_, k)| k.used).map(|(id, _)| *id) else { break };
            self.kept.remove(&oldest);
        }
    }

    /// Conversations kept.
    pub fn len(&self) -> usize {
        self.kept.len()
    }
    pub fn is_empty(&self) -> bool {
        self.kept.is_empty()
    }
}

/// A scope in words, for errors; a view's camera is called `camera`.
fn describe(scope: &Scope, names: &ObjectNames, camera: &str) -> String {
    match scope {
        Scope::View(_) => format!("the view from {camera}"),
        Scope::Object { id, .. } => format!("object {id} ({}) seen from {camera}", names.name(*id)),
        Scope::Scene { views } => format!("the scene through {views} views"),
    }
}
