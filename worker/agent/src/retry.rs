//! Waiting: the exponential backoff between retries, the shutdown signal every wait listens to,
//! and how gRPC failures are classified and described.

use std::future::Future;
use std::time::Duration;
use tokio::sync::watch;
use tonic::{Code, Status};

/// Delays of 0.5 s, doubling up to 10 s.
#[derive(Debug, Clone)]
pub(crate) struct Backoff {
    next: Duration,
}

impl Backoff {
    pub const FIRST: Duration = Duration::from_millis(500);
    pub const MAX: Duration = Duration::from_secs(10);

    pub fn new() -> Self {
        Backoff { next: Self::FIRST }
    }

    /// The delay before the next retry; the one after is twice as long (up to [`Self::MAX`]).
    pub fn next_delay(&mut self) -> Duration {
        let delay = self.next;
        self.next = (self.next * 2).min(Self::MAX);
        delay
    }

    /// Back to the first delay, after a success.
    pub fn reset(&mut self) {
        self.next = Self::FIRST;
    }
}

/// The agent's view of the shutdown request.
#[derive(Debug, Clone)]
pub(crate) struct Stop(watch::Receiver<bool>);

impl Stop {
    pub fn new(receiver: watch::Receiver<bool>) -> Self {
        Stop(receiver)
    }

    /// Shutdown has been asked for.
    pub fn requested(&self) -> bool {
        *self.0.borrow()
    }

    /// Resolves when shutdown is asked for.
    pub async fn wait(&mut self) {
        if self.0.wait_for(|stop| *stop).await.is_err() {
            // The sender lives as long as the agent runs: without it nothing can stop us.
            std::future::pending::<()>().await;
        }
    }

    /// Sleeps for `delay` or until shutdown; true when shutdown cut it short (or came before).
    pub async fn sleep(&mut self, delay: Duration) -> bool {
        tokio::select! {
            () = tokio::time::sleep(delay) => self.requested(),
            () = self.wait() => true,
        }
    }
}

/// The call, or `DeadlineExceeded` when it has not answered within `limit`.
pub(crate) async fn within<T>(
    limit: Duration,
    call: impl Future<Output = Result<tonic::Response<T>, Status>>,
) -> Result<T, Status> {
    match tokio::time::timeout(limit, call).await {
        Ok(result) => result.map(tonic::Response::into_inner),
        Err(_) => Err(Status::deadline_exceeded(format!(
            "no answer within {} s",
            limit.as_secs_f64()
        ))),
    }
}

/// The coordinator does not accept our credentials: retrying cannot help.
pub(crate) fn is_auth_failure(status: &Status) -> bool {
    matches!(
        status.code(),
        Code::Unauthenticated | Code::PermissionDenied
    )
}

/// A failure of the network or of a coordinator that is (re)starting: worth retrying the call.
pub(crate) fn is_transient(status: &Status) -> bool {
    matches!(
        status.code(),
        Code::Unavailable
            | Code::DeadlineExceeded
            | Code::Aborted
            | Code::Cancelled
            | Code::Unknown
            | Code::Internal
    )
}

/// `Code: message: cause: cause…`, for logs.
pub(crate) fn describe(status: &Status) -> String {
    let head = if status.message().is_empty() {
        format!("{:?}", status.code())
    } else {
        format!("{:?}: {}", status.code(), status.message())
    };
    with_causes(head, std::error::Error::source(status))
}

/// An error and its chain of causes on one line.
pub(crate) fn error_chain(error: &dyn std::error::Error) -> String {
    with_causes(error.to_string(), error.source())
}

fn with_causes(mut text: String, mut cause: Option<&dyn std::error::Error>) -> String {
    while let Some(e) = cause {
        let part = e.to_string();
        if !text.contains(&part) {
            text.push_str(": ");
            text.push_str(&part);
        }
        cause = e.source();
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_to_ten_seconds_and_resets() {
        let mut b = Backoff::new();
        let delays: Vec<f64> = (0..7).map(|_| b.next_delay().as_secs_f64()).collect();
        assert_eq!(delays, [0.5, 1.0, 2.0, 4.0, 8.0, 10.0, 10.0]);
        b.reset();
        assert_eq!(b.next_delay(), Backoff::FIRST);
    }

    #[test]
    fn failures_are_classified() {
        assert!(is_transient(&Status::unavailable("down")));
        assert!(!is_transient(&Status::failed_precondition("stale")));
        assert!(is_auth_failure(&Status::unauthenticated("token")));
        assert_eq!(
            describe(&Status::not_found("worker w1")),
            "NotFound: worker w1"
        );
    }

    #[tokio::test]
    async fn sleep_is_cut_short_by_shutdown() {
        let (tx, rx) = watch::channel(false);
        let mut stop = Stop::new(rx);
        assert!(!stop.sleep(Duration::from_millis(1)).await);
        tx.send(true).unwrap();
        let start = std::time::Instant::now();
        assert!(stop.sleep(Duration::from_secs(30)).await);
        assert!(start.elapsed() < Duration::from_secs(5));
        assert!(stop.requested());
    }
}
