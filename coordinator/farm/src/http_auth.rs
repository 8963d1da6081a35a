//! The web face's token check. When the coordinator has a token, every page, `/metrics` and
//! every map need it, presented as gRPC takes it (`Authorization: Bearer <token>`, as Prometheus
//! sends it with `authorization: { credentials_file: ... }`) or as the `scatterfarm_token`
//! cookie, which `/login` sets from a form (an HttpOnly, SameSite=Strict cookie, so a browser
//! sends it to this coordinator only; `Secure` when the web face serves HTTPS, so a browser never
//! sends it over plain HTTP). Without a token, or with `--http-open`, nothing is checked.

use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::middleware::Next;
use axum::response::{Html, IntoResponse, Redirect, Response};
use axum::Form;
use scatterfarm_proto::auth::constant_time_eq;
use std::sync::Arc;

/// The cookie `/login` sets.
pub const COOKIE: &str = "scatterfarm_token";

/// The token the web face asks for; `None` lets everyone in.
#[derive(Clone, Default)]
pub struct WebToken(pub Option<Arc<str>>);

impl WebToken {
    fn accepts(&self, presented: &str) -> bool {
        match &self.0 {
            None => true,
            Some(t) => constant_time_eq(presented.as_bytes(), t.as_bytes()),
        }
    }
}

/// The token a request presents: its bearer header, else its cookie.
fn presented(headers: &HeaderMap) -> Option<String> {
    if let Some(v) = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
    {
        return v.strip_prefix("Bearer ").map(|t| t.trim().to_string());
    }
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .filter_map(|c| c.trim().split_once('='))
        .find(|(k, _)| *k == COOKIE)
        .map(|(_, v)| v.to_string())
}

const LOGIN_FORM: &str = "<!doctype html><html><head><meta charset=\"utf-8\"><title>scatterfarm: token</title></head><body><h1>scatterfarm</h1><p>This coordinator needs its token (the first line of its <code>--token-file</code>).</p><form method=\"post\" action=\"/login\"><input type=\"password\" name=\"token\" autofocus> <button type=\"submit\">Open</button></form></body></html>";

/// Lets a request through when it presents the token; else 401 with the login form for a
/// browser (or a plain reason for anything else).
pub async fn require(State(token): State<WebToken>, request: Request, next: Next) -> Response {
    if token.0.is_none() {
        return next.run(request).await;
    }
    match presented(request.headers()) {
        Some(p) if token.accepts(&p) => next.run(request).await,
        Some(_) => (StatusCode::UNAUTHORIZED, "wrong token").into_response(),
        None => {
            let browser = request
                .headers()
                .get(header::ACCEPT)
                .and_then(|v| v.to_str().ok())
                .is_some_and(|a| a.contains("text/html"));
            if browser {
                (StatusCode::UNAUTHORIZED, Html(LOGIN_FORM)).into_response()
            } else {
                (
                    StatusCode::UNAUTHORIZED,
                    "this coordinator requires its token: send `Authorization: Bearer <token>`, \
                     or log in at /login",
                )
                    .into_response()
            }
        }
    }
}

/// What `/login` needs: the token, and whether the web face serves HTTPS (then the cookie is
/// `Secure`).
#[derive(Clone, Default)]
pub struct LoginSettings {
    pub token: WebToken,
    pub secure_cookie: bool,
}

/// The login form's field.
#[derive(serde::Deserialize)]
pub struct Login {
    token: String,
}

/// `GET /login`: the form.
pub async fn login_form() -> Html<&'static str> {
    Html(LOGIN_FORM)
}

/// `POST /login`: sets the cookie when the token is right, and goes to the status page.
pub async fn login(State(settings): State<LoginSettings>, Form(login): Form<Login>) -> Response {
    let token = &settings.token;
    let t = login.token.trim();
    if token.0.is_none() || !token.accepts(t) || t.contains([';', ',', ' ']) {
        return (StatusCode::UNAUTHORIZED, Html(LOGIN_FORM)).into_response();
    }
    let secure = if settings.secure_cookie {
        "; Secure"
    } else {
        ""
    };
    (
        [(
            header::SET_COOKIE,
            format!("{COOKIE}={t}; HttpOnly; SameSite=Strict; Path=/{secure}"),
        )],
        Redirect::to("/"),
    )
        .into_response()
}
