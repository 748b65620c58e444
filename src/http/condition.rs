//! `GET /api/drives/{name}/condition`: a drive's condition checks (oldest first) and alarms.

use axum::extract::State;
use axum::response::Response;

use super::{ApiError, AppState, Segment, json_response};

pub(super) async fn condition(State(s): State<AppState>, Segment(name): Segment) -> Result<Response, ApiError> {
    let c =
        s.service.condition(&name).ok_or_else(|| ApiError::not_found(format!("no drive {}", super::echo(&name))))?;
    let body = c.to_json();
    Ok(json_response(&body, 4096))
}
