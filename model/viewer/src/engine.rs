//! The one inference thread: it opens the [`ChatSession`] (one model in memory, never shared
//! between threads) and serves two queues. Quick jobs (pick, select, render, question checks) go
//! first, and also run between the decoding steps of an answer, so a click is answered while
//! another client's answer streams. Questions wait in a bounded queue in arrival order (a full
//! queue is refused: the server answers 503) and stream their answer as [`AskEvent`]s; a client
//! that goes away (its event channel closes) stops its generation at the next step, or before it
//! starts.

use crate::conversations::Conversations;
pub use crate::conversations::Scope;
use crate::error::ApiError;
use crate::scene_info::ObjectNames;
use crate::splat_files::SplatFiles;
use model::ObjectId;
use model::chat::{ChatSession, Conversation, Picked, Target};
use model::find::Finder;
use model::splats::SplatModel;
use model::vlm::GenerateOptions;
use serde::Serialize;
use splat_kernels::Camera;
use std::collections::VecDeque;
use std::ops::ControlFlow;
use std::sync::{Arc, Condvar, Mutex};
use std::time::Instant;
use tokio::sync::{mpsc, oneshot, watch};

/// An object in a view: what a pick or a select answers.
#[derive(Clone, Debug, Serialize)]
pub struct ObjectReply {
    pub id: ObjectId,
    pub name: String,
    /// Pixels of the object in the view.
    pub pixels: usize,
    /// The crop box `[x0, y0, x1, y1)` (the mask's box + the teacher's margin).
    pub bbox: [usize; 4],
    pub mask: Mask,
}

/// A run-length mask of a `width x height` view: `runs` = `[start, length, ...]` over row-major
/// pixel indices.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Mask {
    pub width: u32,
    pub height: u32,
    pub runs: Vec<u32>,
}

impl Mask {
    /// The pixels of `ids` equal to `id`.
    pub fn of(ids: &[ObjectId], id: ObjectId, width: u32, height: u32) -> Self {
        let mut runs = Vec::new();
        let mut p = 0;
        while p < ids.len() {
            if ids[p] == id {
                let start = p;
                while p < ids.len() && ids[p] == id {
                    p += 1;
                }
                runs.extend([start as u32, (p - start) as u32]);
            } else {
                p += 1;
            }
        }
        Self { width, height, runs }
    }
}

/// Work answered at once.
pub enum Quick {
    /// The object under pixel `(x, y)` of the view from `camera`.
    Pick { camera: Camera, x: usize, y: usize },
    /// Object `id` followed to the view from `camera`.
    Select { camera: Camera, id: ObjectId },
    /// The view from `camera` as RGB bytes `[H, W, 3]`, without the Gaussians of the objects in
    /// `hidden` (checked: objects of the scene).
    Render { camera: Camera, hidden: Vec<ObjectId> },
    /// Whether `question` can be asked about `scope` (in `conversation`, when given): resolves
    /// the scope (an object must be visible), checks the conversation is kept and about the same
    /// scope, and measures the question against the model's context.
    Check { scope: Scope, question: String, conversation: Option<u64> },
    /// The scene's objects scored against `phrase`, with the masks at `camera` of those scoring
    /// at least `threshold`.
    Find { phrase: String, threshold: f32, camera: Camera },
}

/// The answer to a [`Quick`] job.
pub enum QuickReply {
    Object(Option<ObjectReply>),
    Frame(Vec<u8>),
    /// The question can be asked.
    Checked,
    Found(Found),
}

/// What a search answers: every object scored, best first, and the matches' masks.
#[derive(Clone, Debug, Serialize)]
pub struct Found {
    pub query: String,
    pub threshold: f32,
    /// The objects at or above the threshold, best first, each with its mask at the camera
    /// (`null` where it is hidden there).
    pub matches: Vec<FoundObject>,
    /// Every object searched, best first (no masks).
    pub ranked: Vec<FoundObject>,
    /// Seconds building the objects' tokens (the first search only) and scoring, in ms.
    pub setup_ms: f64,
    pub score_ms: f64,
}

/// An object scored against a phrase.
#[derive(Clone, Debug, Serialize)]
pub struct FoundObject {
    pub id: ObjectId,
    pub name: String,
    pub score: f32,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mask: Option<Option<Mask>>,
}

/// An event of a streamed answer (one server-sent event each; the name is the variant's).
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum AskEvent {
    /// Waiting: `ahead` questions are before this one (the one being answered included); sent
    /// when the request is queued behind others and each time one of them finishes.
    Queued { ahead: u64 },
    /// Answering started: the tokens of the target are ready. `conversation` is the id to send
    /// with a follow-up; `turn` counts its questions (1 = the first); `cached_tokens` of the
    /// `prompt_tokens` were kept from the earlier turns (not prefilled again); `dropped` oldest
    /// exchanges were dropped to fit the model's context.
    Start {
        ticket: u64,
        conversation: u64,
        turn: usize,
        queue_ms: f64,
        tokens_ms: f64,
        prompt_tokens: usize,
        cached_tokens: usize,
        dropped: usize,
        /// Set when the model was trained on question forms (`model::known`) and this question
        /// takes none of them: its answer is a guess, and the page says so beside it.
        #[serde(skip_serializing_if = "Option::is_none")]
        unknown_form: Option<String>,
    },
    /// New answer text.
    Token { text: String },
    /// The answer is complete.
    Done {
        text: String,
        /// A list answer's items ("red cube blue cone": "red cube", "blue cone"), which the page
        /// shows with separators; `None` for any other answer.
        #[serde(skip_serializing_if = "Option::is_none")]
        items: Option<Vec<String>>,
        tokens: usize,
        first_token_ms: f64,
        tokens_per_s: f64,
        total_ms: f64,
        stopped: bool,
        cancelled: bool,
    },
    /// The question could not be answered.
    Error { error: String, status: u16 },
}

/// A question waiting for its turn.
pub struct AskJob {
    pub scope: Scope,
    pub question: String,
    /// The conversation it follows up (`None`: a new one).
    pub conversation: Option<u64>,
    pub opts: GenerateOptions,
    pub events: mpsc::Sender<AskEvent>,
    /// When the request arrived.
    pub arrived: Instant,
}

struct QuickJob {
    work: Quick,
    reply: oneshot::Sender<Result<QuickReply, ApiError>>,
}

#[derive(Default)]
struct Queued {
    quick: VecDeque<QuickJob>,
    asks: VecDeque<(u64, AskJob)>,
    next_ticket: u64,
    closed: bool,
}

/// The queues between the HTTP handlers and the inference thread.
pub struct Queues {
    state: Mutex<Queued>,
    wake: Condvar,
    /// Most questions waiting (the one being answered not counted).
    pub capacity: usize,
    /// Most quick jobs waiting.
    pub quick_capacity: usize,
    /// The ticket of the last question answered (or given up: its client went away).
    finished: watch::Sender<u64>,
}

impl Queues {
    pub fn new(capacity: usize, quick_capacity: usize) -> Arc<Self> {
        Arc::new(Self {
            state: Mutex::default(),
            wake: Condvar::new(),
            capacity,
            quick_capacity,
            finished: watch::channel(0).0,
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Queued> {
        // a panic elsewhere while holding the lock leaves plain queues: still usable
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queues a question; `(ticket, questions ahead)`, or `None` when the queue is full or closed.
    pub fn push_ask(&self, job: AskJob) -> Option<(u64, u64)> {
        let mut q = self.lock();
        if q.closed || q.asks.len() >= self.capacity {
            return None;
        }
        q.next_ticket += 1;
        let ticket = q.next_ticket;
        q.asks.push_back((ticket, job));
        // read while the job is still held here: once the lock is let go the inference thread may
        // answer it before this line runs, and the last finished ticket would be this one
        let ahead = ticket - 1 - *self.finished.borrow();
        drop(q);
        self.wake.notify_one();
        Some((ticket, ahead))
    }

    /// Runs `work` on the inference thread and waits for its answer.
    pub async fn quick(&self, work: Quick) -> Result<QuickReply, ApiError> {
        let (tx, rx) = oneshot::channel();
        {
            let mut q = self.lock();
            if q.closed {
                return Err(ApiError::status(axum::http::StatusCode::SERVICE_UNAVAILABLE, "the server is stopping"));
            }
            if q.quick.len() >= self.quick_capacity {
                return Err(ApiError::status(
                    axum::http::StatusCode::SERVICE_UNAVAILABLE,
                    format!("{} requests are waiting already; try again", q.quick.len()),
                ));
            }
            q.quick.push_back(QuickJob { work, reply: tx });
        }
        self.wake.notify_one();
        rx.await.unwrap_or_else(|_| Err(ApiError::internal("the inference thread stopped")))
    }

    /// Watches the ticket of the last question answered (a waiting client's queue position).
    pub fn finished(&self) -> watch::Receiver<u64> {
        self.finished.subscribe()
    }

    /// Stops taking work; the inference thread ends after the job in hand. Waiting jobs are
    /// dropped, which ends their clients' streams (and answers their requests with an error).
    pub fn close(&self) {
        let dropped = {
            let mut q = self.lock();
            q.closed = true;
            (std::mem::take(&mut q.quick), std::mem::take(&mut q.asks))
        };
        drop(dropped);
        self.wake.notify_all();
    }

    fn is_closed(&self) -> bool {
        self.lock().closed
    }

    fn pop_quick(&self) -> Option<QuickJob> {
        self.lock().quick.pop_front()
    }

    /// The next job, quick ones first; `None` once closed.
    fn next(&self) -> Option<Result<QuickJob, (u64, AskJob)>> {
        let mut q = self.lock();
        loop {
            if q.closed {
                return None;
            }
            if let Some(j) = q.quick.pop_front() {
                return Some(Ok(j));
            }
            if let Some(j) = q.asks.pop_front() {
                return Some(Err(j));
            }
            q = self.wake.wait(q).unwrap_or_else(|e| e.into_inner());
        }
    }
}

/// The inference thread's state: the session, and what quick jobs need beside it.
pub struct Engine {
    session: ChatSession,
    quick: QuickState,
}

/// Object names, the objects picked lately (each holds its view's identity map and, once asked
/// about, its tokens, kept for follow-up questions), the conversations and the search's objects
/// (made at the first search).
struct QuickState {
    names: ObjectNames,
    picks: VecDeque<Picked>,
    conversations: Conversations,
    finder: Option<Finder>,
    files: Arc<SplatFiles>,
    /// The Gaussians shown without the objects last hidden, and those objects.
    hidden: Option<(Vec<ObjectId>, SplatModel)>,
}

/// Picks kept.
const KEPT_PICKS: usize = 16;

impl Engine {
    /// The engine of `session`; `files` says which Gaussians are each object's (for hidden objects).
    pub fn new(session: ChatSession, names: ObjectNames, files: Arc<SplatFiles>) -> Self {
        let (picks, conversations) = (VecDeque::new(), Conversations::default());
        Self { session, quick: QuickState { names, picks, conversations, finder: None, files, hidden: None } }
    }

    /// Serves `queues` until they close.
    pub fn run(mut self, queues: &Queues) {
        while let Some(job) = queues.next() {
            match job {
                Ok(q) => self.quick.serve(&self.session, q),
                Err((ticket, ask)) => {
                    let events = ask.events.clone();
                    // a client that went away while waiting is skipped
                    if !events.is_closed() {
                        let r = model::catch_backend("generation", || self.answer(ticket, ask, queues))
                            .map_err(|e| ApiError::from_model(e, None))
                            .and_then(|r| r);
                        if let Err(e) = r {
                            let _ = events
                                .blocking_send(AskEvent::Error { error: e.to_string(), status: e.status.as_u16() });
                        }
                    }
                    queues.finished.send_replace(ticket);
                }
            }
        }
    }

    fn answer(&mut self, ticket: u64, job: AskJob, queues: &Queues) -> Result<(), ApiError> {
        let Engine { session, quick } = self;
        let t0 = Instant::now();
        let (id, mut conversation) = match job.conversation {
            Some(id) => (id, quick.conversations.take(id, &job.scope, &quick.names)?),
            None => {
                let target = quick.target(session, &job.scope)?;
                (quick.conversations.start(&job.scope), Conversation::new(target))
            }
        };
        let r = Self::converse(session, quick, &mut conversation, (ticket, id), &job, queues, t0);
        quick.conversations.put_back(id, conversation);
        r
    }

    /// Answers `job` in `conversation` (`ids`: the job's ticket and the conversation's id).
    fn converse(
        session: &ChatSession,
        quick: &mut QuickState,
        conversation: &mut Conversation,
        (ticket, id): (u64, u64),
        job: &AskJob,
        queues: &Queues,
        t0: Instant,
    ) -> Result<(), ApiError> {
        let next = session
            .next_turn(conversation, &job.question, &job.opts)
            .map_err(|e| ApiError::from_model(e, Some("question")))?;
        let t1 = Instant::now();
        let start = AskEvent::Start {
            ticket,
            conversation: id,
            turn: conversation.exchanges().len() + conversation.dropped() + 1,
            queue_ms: ms(job.arrived, t0),
            tokens_ms: ms(t0, t1),
            prompt_tokens: next.prompt_tokens(),
            cached_tokens: next.cached_tokens,
            dropped: next.dropped,
            unknown_form: model::known::unknown_question_note(&session.vlm, &conversation.target, &job.question),
        };
        if job.events.blocking_send(start).is_err() {
            return Ok(());
        }
        let mut first: Option<Instant> = None;
        let reply = session
            .answer_turn(conversation, next, &job.opts, |piece| {
                first.get_or_insert_with(Instant::now);
                // clicks and renders of other clients are answered between two tokens
                while let Some(q) = queues.pop_quick() {
                    quick.serve(session, q);
                }
                let gone = job.events.is_closed()
                    || queues.is_closed()
                    || (!piece.is_empty()
                        && job.events.blocking_send(AskEvent::Token { text: piece.to_string() }).is_err());
                if gone { ControlFlow::Break(()) } else { ControlFlow::Continue(()) }
            })
            .map_err(|e| ApiError::from_model(e, Some("question")))?;
        let g = reply.generation;
        let end = Instant::now();
        let first = first.unwrap_or(end);
        let decode_s = (end - first).as_secs_f64();
        let _ = job.events.blocking_send(AskEvent::Done {
            tokens: g.ids.len(),
            first_token_ms: ms(job.arrived, first),
            tokens_per_s: if g.ids.len() > 1 && decode_s > 0.0 { (g.ids.len() - 1) as f64 / decode_s } else { 0.0 },
            total_ms: ms(job.arrived, end),
            stopped: g.stopped,
            cancelled: g.cancelled,
            items: model::known::forms(&session.vlm).and_then(|_| model::data::synth::forms::list_items(&g.text)),
            text: g.text,
        });
        Ok(())
    }
}

impl QuickState {
    fn serve(&mut self, session: &ChatSession, job: QuickJob) {
        if job.reply.is_closed() {
            return; // the client went away
        }
        let reply = model::catch_backend("the request", || self.work(session, job.work))
            .map_err(|e| ApiError::from_model(e, None))
            .and_then(|r| r);
        let _ = job.reply.send(reply);
    }

    fn work(&mut self, session: &ChatSession, work: Quick) -> Result<QuickReply, ApiError> {
        let err = |field: &'static str| move |e| ApiError::from_model(e, Some(field));
        match work {
            Quick::Pick { camera, x, y } => {
                let picked = session.click(&camera, x, y).map_err(err("x"))?;
                Ok(QuickReply::Object(picked.map(|p| self.keep(p))))
            }
            Quick::Select { camera, id } => {
                let picked = self.resolve(session, &camera, id).map_err(err("id"))?;
                Ok(QuickReply::Object(picked.map(|p| self.reply(&p))))
            }
            Quick::Render { camera, hidden } => {
                let rgb = if hidden.is_empty() {
                    session.view_image(&camera, None)
                } else {
                    let scene = &session.scene;
                    if self.hidden.as_ref().is_none_or(|(ids, _)| *ids != hidden) {
                        let keep = self.files.kept(&hidden, "hidden")?;
                        self.hidden = Some((hidden, scene.shown().rows(&keep)));
                    }
                    let (_, shown) = self.hidden.as_ref().expect("set above");
                    shown.render_rgb(&camera, scene.sh_degree, scene.background)
                };
                Ok(QuickReply::Frame(rgb.map_err(err("camera"))?.iter().map(|v| (v * 255.0 + 0.5) as u8).collect()))
            }
            Quick::Find { phrase, threshold, camera } => {
                Ok(QuickReply::Found(self.find(session, phrase, threshold, &camera)?))
            }
            Quick::Check { scope, question, conversation } => {
                if let Some(id) = conversation {
                    self.conversations.check(id, &scope, &self.names)?;
                }
                let images = self.target(session, &scope)?.images();
                session.check_question(&question, images).map_err(err("question"))?;
                Ok(QuickReply::Checked)
            }
        }
    }

    fn find(
        &mut self,
        session: &ChatSession,
        phrase: String,
        threshold: f32,
        camera: &Camera,
    ) -> Result<Found, ApiError> {
        let err = |field: &'static str| move |e| ApiError::from_model(e, Some(field));
        let t0 = Instant::now();
        if self.finder.is_none() {
            self.finder = Some(Finder::new(session, &self.names).map_err(err("phrase"))?);
        }
        let finder = self.finder.as_mut().expect("made above");
        let t1 = Instant::now();
        let ranked = finder.rank(session, &phrase).map_err(err("phrase"))?;
        let t2 = Instant::now();
        let hits: Vec<_> = ranked.iter().filter(|r| r.score >= threshold).collect();
        let ids = if hits.is_empty() {
            Vec::new()
        } else {
            session.scene.splats.render_ids(camera).map_err(err("camera"))?
        };
        let object = |id: ObjectId, score: f32, mask: Option<Option<Mask>>| FoundObject {
            id,
            name: self.names.name(id),
            score,
            mask,
        };
        let matches = hits
            .iter()
            .map(|r| {
                let shown = ids.contains(&r.id).then(|| Mask::of(&ids, r.id, camera.width, camera.height));
                object(r.id, r.score, Some(shown))
            })
            .collect();
        Ok(Found {
            query: phrase,
            threshold,
            matches,
            ranked: ranked.iter().map(|r| object(r.id, r.score, None)).collect(),
            setup_ms: ms(t0, t1),
            score_ms: ms(t1, t2),
        })
    }

    /// Keeps a pick (for follow-up questions) and describes it.
    /// A pick of an object already kept from the same camera keeps the old one (and its tokens).
    fn keep(&mut self, p: Picked) -> ObjectReply {
        let reply = self.reply(&p);
        let kept = match self.picks.iter().position(|k| k.camera == p.camera && k.id == p.id) {
            Some(i) => self.picks.remove(i).expect("found"),
            None => p,
        };
        self.picks.push_front(kept);
        self.picks.truncate(KEPT_PICKS);
        reply
    }

    fn reply(&self, p: &Picked) -> ObjectReply {
        ObjectReply {
            id: p.id,
            name: self.names.name(p.id),
            pixels: p.pixels(),
            bbox: p.bbox,
            mask: Mask::of(&p.ids, p.id, p.camera.width, p.camera.height),
        }
    }

    /// Object `id` seen from `camera`: a kept pick when there is one (its tokens too), else
    /// resolved now and kept; `None` when the object is not visible there.
    fn resolve(&mut self, session: &ChatSession, camera: &Camera, id: ObjectId) -> model::Result<Option<Picked>> {
        let found = self.picks.iter().find(|p| p.camera == *camera && p.id == id).cloned();
        let Some(p) = found.map_or_else(|| session.select(camera, id), |p| Ok(Some(p)))? else { return Ok(None) };
        self.keep(p.clone());
        Ok(Some(p))
    }

    fn target(&mut self, session: &ChatSession, scope: &Scope) -> Result<Target, ApiError> {
        match scope {
            Scope::View(c) => Ok(Target::View(*c)),
            Scope::Object { camera, id } => match self.resolve(session, camera, *id) {
                Ok(Some(p)) => Ok(Target::Object(p)),
                // an id no Gaussian holds is no object at all, not one out of sight
                Ok(None) if !session.scene.splats.gaussian_classes().contains(id) => {
                    Err(ApiError::field("id", format!("the scene has no object {id}")))
                }
                Ok(None) => Err(ApiError::field(
                    "id",
                    format!("object {id} ({}) is not visible from this camera", self.names.name(*id)),
                )),
                Err(e) => Err(ApiError::from_model(e, Some("id"))),
            },
            Scope::Scene { views } => session.scene_target(*views).map_err(|e| ApiError::from_model(e, Some("views"))),
        }
    }
}

fn ms(a: Instant, b: Instant) -> f64 {
    (b - a).as_secs_f64() * 1e3
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job() -> (AskJob, mpsc::Receiver<AskEvent>) {
        let (tx, rx) = mpsc::channel(4);
        let camera = Camera::new(glam::Mat4::IDENTITY, 10.0, 10.0, 8, 8);
        let job = AskJob {
            scope: Scope::View(camera),
            question: "q".into(),
            conversation: None,
            opts: GenerateOptions::default(),
            events: tx,
            arrived: Instant::now(),
        };
        (job, rx)
    }

    #[test]
    fn the_question_queue_is_bounded_ordered_and_emptied_on_close() {
        let q = Queues::new(2, 4);
        let (a, _ra) = job();
        let (b, mut rb) = job();
        let (c, _rc) = job();
        assert_eq!(q.push_ask(a), Some((1, 0)), "first ticket, nobody ahead");
        assert_eq!(q.push_ask(b), Some((2, 1)), "one ahead");
        assert!(q.push_ask(c).is_none(), "the queue holds 2");
        // the inference thread takes them in order
        let Some(Err((ticket, _))) = q.next() else { panic!("an ask") };
        assert_eq!(ticket, 1);
        q.finished.send_replace(1);
        let (d, _rd) = job();
        assert_eq!(q.push_ask(d), Some((3, 1)), "ticket 2 is ahead of it");
        // closing drops what waits: its client's stream ends
        q.close();
        assert!(q.next().is_none());
        assert_eq!(rb.try_recv(), Err(mpsc::error::TryRecvError::Disconnected));
        let (e, _re) = job();
        assert!(q.push_ask(e).is_none(), "closed");
    }

    #[test]
    fn masks_are_run_length_encoded_row_major() {
        let ids = [0, 3, 3, 1, 3, 0, 0, 3, 3];
        let m = Mask::of(&ids, 3, 3, 3);
        assert_eq!(m.runs, vec![1, 2, 4, 1, 7, 2]);
        assert_eq!((m.width, m.height), (3, 3));
        assert!(Mask::of(&ids, 9, 3, 3).runs.is_empty());
    }
}
