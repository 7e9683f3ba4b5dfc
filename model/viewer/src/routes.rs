//! The HTTP API (axum): the page and its files, the scene, pick / select / render, and questions
//! answered as server-sent events. Every request body is JSON with no unknown fields; every error
//! is a 4xx/5xx JSON body naming the field at fault (see [`ApiError`]).
//!
//! | route | body | answer |
//! |---|---|---|
//! | `GET /` and its files | | the page (embedded) |
//! | `GET /api/scene` | | [`SceneInfo`](crate::scene_info::SceneInfo) |
//! | `GET /api/splats.ply?without=3,5`, `.spz` | | the Gaussians, `.ply` or `.spz` (without those objects') |
//! | `GET /api/objects/3.ply`, `3.spz` | | object 3's Gaussians as a download |
//! | `POST /api/pick` | `{camera, x, y}` | `{object: {id, name, pixels, bbox, mask} or null, ms}` |
//! | `POST /api/select` | `{camera, id}` | the same, for an object followed to a new camera |
//! | `POST /api/render` | `{camera, hidden?}` | PNG (chatsplat's own rasterizer; `hidden`: object ids left out) |
//! | `POST /api/find` | `{phrase, camera, threshold?}` | [`Found`](crate::engine::Found): scores, the matches' masks |
//! | `POST /api/ask` | `{scope, camera?, id?, views?, question, conversation?, ...}` | event stream of [`AskEvent`] |
//!
//! A question is the first of a new conversation unless it names one (`conversation`: the id
//! its first answer's `start` event gave, about the same scope): then it is asked after that
//! conversation's earlier questions and answers ([`conversations`](crate::conversations)).

use crate::assets;
use crate::camera::ViewCamera;
use crate::engine::{AskEvent, AskJob, ObjectReply, Queues, Quick, QuickReply, Scope};
use crate::error::ApiError;
use crate::scene_info::ObjectNames;
use crate::splat_files::{Format, SplatFiles, parse_ids};
use axum::Router;
use axum::body::{Body, Bytes};
use axum::extract::rejection::QueryRejection;
use axum::extract::{FromRequest, Path, Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, Method, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use futures_util::Stream;
use model::ObjectId;
use model::vlm::GenerateOptions;
use serde::Deserialize;
use serde::de::DeserializeOwned;
use std::convert::Infallible;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Largest request body, bytes.
pub const MAX_BODY: usize = 64 * 1024;
/// Most views of a scene-level question.
pub const MAX_SCENE_VIEWS: usize = 16;
/// Most new tokens a request may ask for.
pub use model::vlm::MAX_NEW_TOKENS;
/// How long a pick or render may wait for the inference thread.
const QUICK_TIMEOUT: Duration = Duration::from_secs(120);

/// What the handlers share.
pub struct AppState {
    pub queues: Arc<Queues>,
    /// `GET /api/scene`, serialised once.
    pub scene: Bytes,
    pub splats: Arc<SplatFiles>,
    /// The objects' names (download file names).
    pub names: ObjectNames,
    pub max_new_tokens: usize,
    /// Origins (`http://host:port`) allowed to call the API from another page.
    pub allow_origins: Vec<String>,
}

/// The router over `state`.
pub fn router(state: Arc<AppState>) -> Router {
    Router::new()
        .route("/api/scene", get(scene))
        .route("/api/splats.ply", get(|s, q| splats(s, q, Format::Ply)))
        .route("/api/splats.spz", get(|s, q| splats(s, q, Format::Spz)))
        .route("/api/objects/{file}", get(object_file))
        .route("/api/pick", post(pick))
        .route("/api/select", post(select))
        .route("/api/render", post(render))
        .route("/api/ask", post(ask))
        .route("/api/find", post(find))
        .fallback(static_file)
        .method_not_allowed_fallback(|m: Method| async move {
            ApiError::status(StatusCode::METHOD_NOT_ALLOWED, format!("{m} is not allowed here")).into_response()
        })
        .layer(middleware::from_fn_with_state(state.clone(), same_origin))
        .with_state(state)
}

/// A JSON body of at most [`MAX_BODY`] bytes, parsed with the path of the field at fault in
/// its errors.
struct JsonBody<T>(T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequest<S> for JsonBody<T> {
    type Rejection = ApiError;

    async fn from_request(req: Request, _: &S) -> Result<Self, ApiError> {
        let bytes = read_body(req.into_body()).await?;
        let mut de = serde_json::Deserializer::from_slice(&bytes);
        let value = serde_path_to_error::deserialize(&mut de).map_err(|e| {
            let path = e.path().to_string();
            let field = if path == "." { None } else { Some(path) };
            ApiError { status: StatusCode::BAD_REQUEST, field, message: format!("invalid JSON: {}", e.inner()) }
        })?;
        de.end().map_err(|e| ApiError::status(StatusCode::BAD_REQUEST, format!("invalid JSON: {e}")))?;
        Ok(Self(value))
    }
}

/// Bodies over [`MAX_BODY`] are read on (and dropped) up to this size before the 413 is sent,
/// so that the client, still sending, receives the answer rather than a reset connection.
const DRAIN: usize = 1 << 20;

async fn read_body(body: Body) -> Result<Vec<u8>, ApiError> {
    use futures_util::StreamExt;
    let mut stream = body.into_data_stream();
    let (mut bytes, mut seen) = (Vec::new(), 0usize);
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|e| ApiError::status(StatusCode::BAD_REQUEST, format!("reading the body: {e}")))?;
        seen += chunk.len();
        if seen <= MAX_BODY {
            bytes.extend_from_slice(&chunk);
        } else if seen > DRAIN {
            break;
        }
    }
    if seen > MAX_BODY {
        return Err(ApiError::status(
            StatusCode::PAYLOAD_TOO_LARGE,
            format!("the request body is over {MAX_BODY} bytes"),
        ));
    }
    Ok(bytes)
}

/// Refuses requests from other origins (a page elsewhere calling this API) unless allowed;
/// answers allowed origins' preflight requests.
async fn same_origin(State(s): State<Arc<AppState>>, req: Request, next: Next) -> Response {
    let headers = req.headers();
    let origin = headers.get(header::ORIGIN).and_then(|o| o.to_str().ok()).map(String::from);
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok()).unwrap_or("");
    let cross_site = headers.get("sec-fetch-site").is_some_and(|v| v == "cross-site");
    let allowed = origin.as_ref().filter(|o| s.allow_origins.iter().any(|a| a == *o));
    let same = origin.as_ref().is_none_or(|o| o.strip_prefix("http://") == Some(host)) && !cross_site;
    match (same, allowed) {
        (_, Some(o)) => {
            let o = HeaderValue::from_str(o).unwrap_or(HeaderValue::from_static("null"));
            let mut r = if req.method() == Method::OPTIONS {
                StatusCode::NO_CONTENT.into_response()
            } else {
                next.run(req).await
            };
            let h = r.headers_mut();
            h.insert(header::ACCESS_CONTROL_ALLOW_ORIGIN, o);
            h.insert(header::ACCESS_CONTROL_ALLOW_HEADERS, HeaderValue::from_static("content-type"));
            h.insert(header::ACCESS_CONTROL_ALLOW_METHODS, HeaderValue::from_static("GET, POST"));
            r
        }
        (true, None) => next.run(req).await,
        (false, None) => ApiError::status(
            StatusCode::FORBIDDEN,
            format!(
                "cross-origin request from {} refused (serve --allow-origin lets an origin in)",
                origin.as_deref().unwrap_or("another site")
            ),
        )
        .into_response(),
    }
}

async fn static_file(method: Method, uri: axum::http::Uri) -> Response {
    match (method, assets::find(uri.path())) {
        (Method::GET | Method::HEAD, Some(a)) => {
            ([(header::CONTENT_TYPE, a.content_type), (header::CACHE_CONTROL, "no-cache")], a.bytes).into_response()
        }
        (_, Some(_)) => ApiError::status(StatusCode::METHOD_NOT_ALLOWED, "only GET").into_response(),
        (_, None) => ApiError::status(StatusCode::NOT_FOUND, format!("no such path: {}", uri.path())).into_response(),
    }
}

async fn scene(State(s): State<Arc<AppState>>) -> Response {
    ([(header::CONTENT_TYPE, "application/json")], s.scene.clone()).into_response()
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SplatsQuery {
    /// Object ids separated by commas.
    #[serde(default)]
    without: String,
}

async fn splats(
    State(s): State<Arc<AppState>>,
    query: Result<Query<SplatsQuery>, QueryRejection>,
    format: Format,
) -> Result<Response, ApiError> {
    let Query(q) =
        query.map_err(|e| ApiError::field("without", format!("{e}: the query takes only without=ID,ID,...")))?;
    let hidden = parse_ids(&q.without, "without")?;
    let file = s.splats.without(&hidden, format)?;
    Ok(([(header::CONTENT_TYPE, "application/octet-stream")], file).into_response())
}

/// `GET /api/objects/3.ply` (or `.spz`): object 3's Gaussians, named for a download
/// ("3-red-cone.ply").
async fn object_file(State(s): State<Arc<AppState>>, Path(file): Path<String>) -> Result<Response, ApiError> {
    let bad =
        || ApiError::status(StatusCode::NOT_FOUND, format!("no such file: {file} (objects are ID.ply or ID.spz)"));
    let (id, ext) = file.split_once('.').ok_or_else(bad)?;
    let (id, format) = (id.parse::<ObjectId>().map_err(|_| bad())?, Format::of(ext).ok_or_else(bad)?);
    let ply = s.splats.object(id, format)?;
    let name = SplatFiles::object_file_name(id, &s.names, format);
    let disposition = HeaderValue::from_str(&format!("attachment; filename=\"{name}\""))
        .map_err(|e| ApiError::internal(e.to_string()))?;
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("application/octet-stream")),
            (header::CONTENT_DISPOSITION, disposition),
        ],
        ply,
    )
        .into_response())
}

async fn quick(s: &AppState, work: Quick) -> Result<QuickReply, ApiError> {
    tokio::time::timeout(QUICK_TIMEOUT, s.queues.quick(work))
        .await
        .unwrap_or_else(|_| Err(ApiError::status(StatusCode::SERVICE_UNAVAILABLE, "the model is busy; try again")))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PickBody {
    camera: ViewCamera,
    /// Pixel of the camera's image (fractions allowed: the pixel containing the point).
    x: f64,
    y: f64,
}

fn object_reply(r: QuickReply, t0: Instant) -> Response {
    let object: Option<ObjectReply> = match r {
        QuickReply::Object(o) => o,
        _ => None,
    };
    axum::Json(serde_json::json!({ "object": object, "ms": t0.elapsed().as_secs_f64() * 1e3 })).into_response()
}

async fn pick(State(s): State<Arc<AppState>>, JsonBody(b): JsonBody<PickBody>) -> Result<Response, ApiError> {
    let t0 = Instant::now();
    let camera = b.camera.to_camera("camera")?;
    let pixel = |field: &str, v: f64, size: u32| {
        if v.is_finite() && v >= 0.0 && v < size as f64 {
            Ok(v as usize)
        } else {
            Err(ApiError::field(field, format!("{v} lies outside the image (0 <= {field} < {size})")))
        }
    };
    let (x, y) = (pixel("x", b.x, camera.width)?, pixel("y", b.y, camera.height)?);
    Ok(object_reply(quick(&s, Quick::Pick { camera, x, y }).await?, t0))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SelectBody {
    camera: ViewCamera,
    id: u64,
}

fn object_id(id: u64) -> Result<ObjectId, ApiError> {
    match ObjectId::try_from(id) {
        Ok(id) if id > 0 => Ok(id),
        _ => Err(ApiError::field("id", format!("{id} is not an object id (1..={})", ObjectId::MAX))),
    }
}

async fn select(State(s): State<Arc<AppState>>, JsonBody(b): JsonBody<SelectBody>) -> Result<Response, ApiError> {
    let t0 = Instant::now();
    let camera = b.camera.to_camera("camera")?;
    let id = object_id(b.id)?;
    Ok(object_reply(quick(&s, Quick::Select { camera, id }).await?, t0))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FindBody {
    phrase: String,
    camera: ViewCamera,
    #[serde(default)]
    threshold: Option<f32>,
}

async fn find(State(s): State<Arc<AppState>>, JsonBody(b): JsonBody<FindBody>) -> Result<Response, ApiError> {
    let camera = b.camera.to_camera("camera")?;
    let threshold = b.threshold.unwrap_or(model::find::DEFAULT_THRESHOLD);
    model::find::check_threshold(threshold).map_err(|e| ApiError::field("threshold", e.to_string()))?;
    let phrase = model::find::normalize(&b.phrase).map_err(|e| ApiError::field("phrase", e.to_string()))?;
    let QuickReply::Found(found) = quick(&s, Quick::Find { phrase, threshold, camera }).await? else {
        return Err(ApiError::internal("the search came back empty"));
    };
    Ok(axum::Json(found).into_response())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RenderBody {
    camera: ViewCamera,
    /// Objects left out of the frame (the page's hidden objects).
    #[serde(default)]
    hidden: Vec<ObjectId>,
}

async fn render(State(s): State<Arc<AppState>>, JsonBody(b): JsonBody<RenderBody>) -> Result<Response, ApiError> {
    let t0 = Instant::now();
    let camera = b.camera.to_camera("camera")?;
    let QuickReply::Frame(rgb) = quick(&s, Quick::Render { camera, hidden: b.hidden }).await? else {
        return Err(ApiError::internal("the render came back empty"));
    };
    let render_ms = t0.elapsed().as_secs_f64() * 1e3;
    let png = tokio::task::spawn_blocking(move || model::images::encode_rgb8(camera.width, camera.height, &rgb))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?
        .map_err(|e| ApiError::internal(e.to_string()))?;
    let mut headers = HeaderMap::new();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static("image/png"));
    headers.insert("x-render-ms", HeaderValue::from_str(&format!("{render_ms:.1}")).expect("a number"));
    Ok((headers, Body::from(png)).into_response())
}

#[derive(Deserialize, Clone, Copy, PartialEq, Eq, Debug)]
#[serde(rename_all = "lowercase")]
enum ScopeName {
    View,
    Object,
    Scene,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct AskBody {
    scope: ScopeName,
    #[serde(default)]
    camera: Option<ViewCamera>,
    #[serde(default)]
    id: Option<u64>,
    #[serde(default)]
    views: Option<usize>,
    question: String,
    /// The conversation this question follows up (the id its first answer's `start` event
    /// gave); left out, the question starts a new conversation.
    #[serde(default)]
    conversation: Option<u64>,
    #[serde(default)]
    max_new_tokens: Option<usize>,
    /// Generate `max_new_tokens` tokens whatever the model says (timing runs).
    #[serde(default)]
    ignore_stop: bool,
}

impl AskBody {
    fn scope(&self) -> Result<Scope, ApiError> {
        let camera = || {
            self.camera
                .ok_or_else(|| ApiError::field("camera", format!("{:?} questions need the camera", self.scope)))?
                .to_camera("camera")
        };
        let unused = |field: &str, given: bool| {
            if given {
                Err(ApiError::field(field, format!("does not apply to {:?} questions", self.scope)))
            } else {
                Ok(())
            }
        };
        match self.scope {
            ScopeName::View => {
                unused("id", self.id.is_some())?;
                unused("views", self.views.is_some())?;
                Ok(Scope::View(camera()?))
            }
            ScopeName::Object => {
                unused("views", self.views.is_some())?;
                let id = self.id.ok_or_else(|| ApiError::field("id", "object questions need the object's id"))?;
                Ok(Scope::Object { camera: camera()?, id: object_id(id)? })
            }
            ScopeName::Scene => {
                unused("id", self.id.is_some())?;
                let views = self.views.unwrap_or(model::chat::DEFAULT_SCENE_VIEWS);
                if !(1..=MAX_SCENE_VIEWS).contains(&views) {
                    return Err(ApiError::field("views", format!("{views} is outside 1..={MAX_SCENE_VIEWS}")));
                }
                Ok(Scope::Scene { views })
            }
        }
    }
}

async fn ask(State(s): State<Arc<AppState>>, JsonBody(b): JsonBody<AskBody>) -> Result<Response, ApiError> {
    let arrived = Instant::now();
    let scope = b.scope()?;
    // (a question's length is bounded by the body's and then by the model's context, below)
    if b.question.trim().is_empty() {
        return Err(ApiError::field("question", "is empty"));
    }
    let max_new_tokens = b.max_new_tokens.unwrap_or(s.max_new_tokens);
    if !(1..=MAX_NEW_TOKENS).contains(&max_new_tokens) {
        return Err(ApiError::field("max_new_tokens", format!("{max_new_tokens} is outside 1..={MAX_NEW_TOKENS}")));
    }
    // the target exists (an object is visible) and the prompt fits the context: 4xx now, not
    // an error event after a 200
    let conversation = b.conversation;
    quick(&s, Quick::Check { scope: scope.clone(), question: b.question.clone(), conversation }).await?;
    let (tx, rx) = tokio::sync::mpsc::channel(256);
    let opts = GenerateOptions { max_new_tokens, ignore_stop: b.ignore_stop, ..Default::default() };
    let job = AskJob { scope, question: b.question, conversation, opts, events: tx, arrived };
    let Some((ticket, ahead)) = s.queues.push_ask(job) else {
        return Err(ApiError::status(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("{} questions are waiting already; try again shortly", s.queues.capacity),
        ));
    };
    let stream = events(rx, s.queues.finished(), ticket, ahead);
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()).into_response())
}

/// The answer's events, with the queue position while it waits. Dropping the stream (the client
/// went away) closes `rx`, which stops the generation.
fn events(
    rx: tokio::sync::mpsc::Receiver<AskEvent>,
    finished: tokio::sync::watch::Receiver<u64>,
    ticket: u64,
    ahead: u64,
) -> impl Stream<Item = Result<Event, Infallible>> {
    struct S {
        rx: tokio::sync::mpsc::Receiver<AskEvent>,
        finished: tokio::sync::watch::Receiver<u64>,
        waiting: bool,
        first: Option<AskEvent>,
    }
    let first = (ahead > 0).then_some(AskEvent::Queued { ahead });
    let state = S { rx, finished, waiting: ahead > 0, first };
    futures_util::stream::unfold(state, move |mut st| async move {
        let ev = match st.first.take() {
            Some(ev) => ev,
            None if st.waiting => tokio::select! {
                ev = st.rx.recv() => ev?,
                changed = st.finished.changed() => {
                    let done = if changed.is_ok() { *st.finished.borrow_and_update() } else { ticket };
                    let ahead = ticket.saturating_sub(done + 1);
                    st.waiting = ahead > 0;
                    AskEvent::Queued { ahead }
                }
            },
            None => st.rx.recv().await?,
        };
        if matches!(ev, AskEvent::Start { .. }) {
            st.waiting = false;
        }
        Some((Ok(sse_event(&ev)), st))
    })
}

fn sse_event(ev: &AskEvent) -> Event {
    let name = match ev {
        AskEvent::Queued { .. } => "queued",
        AskEvent::Start { .. } => "start",
        AskEvent::Token { .. } => "token",
        AskEvent::Done { .. } => "done",
        AskEvent::Error { .. } => "error",
    };
    Event::default().event(name).data(serde_json::to_string(ev).unwrap_or_default())
}
