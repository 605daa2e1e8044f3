//! The console's page: one HTML file, one script, one style sheet and an icon, from
//! `broker/console/`, compiled into the binary (`include_bytes!`). No framework, no
//! build step, nothing fetched from elsewhere: a line's admin network is often cut off
//! from the internet, and a page that loads only what the broker serves is one to audit.
//!
//! Every answer carries `Content-Security-Policy: default-src 'self'` (and no inline
//! script or style: the page sets styles through the DOM only), `nosniff`, no referrer,
//! and framing refused. Assets are revalidated (`no-cache` with an `ETag`, the hash of
//! the bytes): a broker upgrade is seen at the next load, an unchanged asset costs a 304.

use std::sync::OnceLock;

use axum::extract::Path;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

/// (name, content type, bytes). `index.html` is served at `/`, the rest under `/console/`.
pub const ASSETS: &[(&str, &str, &[u8])] = &[
    (
        "index.html",
        "text/html; charset=utf-8",
        include_bytes!("../../console/index.html"),
    ),
    (
        "console.js",
        "text/javascript; charset=utf-8",
        include_bytes!("../../console/console.js"),
    ),
    (
        "console.css",
        "text/css; charset=utf-8",
        include_bytes!("../../console/console.css"),
    ),
    (
        "icon.svg",
        "image/svg+xml",
        include_bytes!("../../console/icon.svg"),
    ),
];

/// The policy every console answer carries.
pub const CSP: &str = "default-src 'self'; img-src 'self'; style-src 'self'; \
     script-src 'self'; connect-src 'self'; object-src 'none'; base-uri 'none'; \
     form-action 'none'; frame-ancestors 'none'";

/// Each asset's ETag: FNV-1a of its bytes, computed once.
fn etag(index: usize) -> &'static str {
    static TAGS: OnceLock<Vec<String>> = OnceLock::new();
    let tags = TAGS.get_or_init(|| {
        ASSETS
            .iter()
            .map(|(_, _, bytes)| {
                let mut h: u64 = 0xcbf2_9ce4_8422_2325;
                for b in *bytes {
                    h ^= u64::from(*b);
                    h = h.wrapping_mul(0x0100_0000_01b3);
                }
                format!("\"{h:016x}\"")
            })
            .collect()
    });
    &tags[index]
}

/// Security headers of every console answer.
pub fn secure(response: &mut Response) {
    let h = response.headers_mut();
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CSP),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
}

fn serve(name: &str, request: &HeaderMap) -> Response {
    let Some(index) = ASSETS.iter().position(|(n, _, _)| *n == name) else {
        let mut r = (StatusCode::NOT_FOUND, "no such console asset\n").into_response();
        secure(&mut r);
        return r;
    };
    let (_, content_type, bytes) = ASSETS[index];
    let tag = etag(index);
    let fresh = request
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == tag));
    let mut response = if fresh {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, content_type)], bytes).into_response()
    };
    let h = response.headers_mut();
    if let Ok(tag) = HeaderValue::from_str(tag) {
        h.insert(header::ETAG, tag);
    }
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    secure(&mut response);
    response
}

pub(super) async fn index(request: HeaderMap) -> Response {
    serve("index.html", &request)
}

pub(super) async fn asset(Path(name): Path<String>, request: HeaderMap) -> Response {
    // `index.html` only at `/`.
    if name == "index.html" {
        return serve("", &request);
    }
    serve(&name, &request)
}
