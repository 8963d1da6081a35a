//! The worker's standing with the coordinator: connecting and registering (retrying with
//! backoff), and the heartbeat task that notices when the coordinator has forgotten us.

use super::retry::{describe, error_chain, is_auth_failure, within, Backoff, Stop};
use super::AgentError;
use scatterfarm_proto::channel::{Authed, ConnectError, Endpoint};
use scatterfarm_proto::v1::worker_service_client::WorkerServiceClient;
use scatterfarm_proto::v1::{HeartbeatRequest, RegisterRequest};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::task::JoinHandle;
use tonic::Code;

pub(crate) type Client = WorkerServiceClient<Authed>;

/// How long a Register or Heartbeat may take.
const CALL_TIMEOUT: Duration = Duration::from_secs(30);
/// The heartbeat interval when the coordinator names none.
const DEFAULT_HEARTBEAT: Duration = Duration::from_secs(5);
/// Heartbeats are never sent more often than this.
const MIN_HEARTBEAT: Duration = Duration::from_millis(50);

/// A registration: the worker id the coordinator gave, a client, and the heartbeat task (stopped
/// when the session is dropped).
#[derive(Debug)]
pub(crate) struct Session {
    pub client: Client,
    pub worker_id: String,
    forgotten: Arc<AtomicBool>,
    heartbeat: JoinHandle<()>,
}

impl Session {
    /// A heartbeat said the coordinator no longer knows this worker: register again.
    pub fn is_forgotten(&self) -> bool {
        self.forgotten.load(Ordering::Relaxed)
    }
}

impl Drop for Session {
    fn drop(&mut self) {
        self.heartbeat.abort();
    }
}

/// Opens sessions: connects once (tonic reconnects the channel by itself afterwards) and
/// registers, as often as the coordinator forgets us.
#[derive(Debug)]
pub(crate) struct Connector {
    endpoint: Endpoint,
    request: RegisterRequest,
    /// The engine fingerprint as one string, for the log.
    engine: String,
    client: Option<Client>,
    stop: Stop,
}

impl Connector {
    pub fn new(endpoint: Endpoint, request: RegisterRequest, engine: String, stop: Stop) -> Self {
        Connector {
            endpoint,
            request,
            engine,
            client: None,
            stop,
        }
    }

    pub fn url(&self) -> &str {
        &self.endpoint.url
    }

    /// Connects if needed and registers, retrying with backoff until it works or shutdown is
    /// asked for (`None`). A refused token, a refused registration (another protocol version)
    /// and a malformed URL or TLS setting are errors.
    pub async fn session(&mut self) -> Result<Option<Session>, AgentError> {
        let mut backoff = Backoff::new();
        loop {
            if self.stop.requested() {
                return Ok(None);
            }
            let failure = match self.connected().await? {
                Err(why) => format!("cannot connect to the coordinator at {}: {why}", self.url()),
                Ok(client) => match self.register(client).await? {
                    Ok(session) => return Ok(Some(session)),
                    Err(why) => format!(
                        "cannot register with the coordinator at {}: {why}",
                        self.url()
                    ),
                },
            };
            let delay = backoff.next_delay();
            tracing::warn!("{failure}; retrying in {:.1} s", delay.as_secs_f64());
            if self.stop.sleep(delay).await {
                return Ok(None);
            }
        }
    }

    /// The client, connecting first if there is none; why not when unreachable.
    async fn connected(&mut self) -> Result<Result<Client, String>, AgentError> {
        if let Some(client) = &self.client {
            return Ok(Ok(client.clone()));
        }
        match self.endpoint.connect().await {
            Ok(channel) => {
                let client = Endpoint::worker_client(channel);
                self.client = Some(client.clone());
                Ok(Ok(client))
            }
            // The message names the URL again: give its causes only.
            Err(ConnectError::Unreachable { source, .. }) => Ok(Err(error_chain(&source))),
            Err(e) => Err(AgentError::Connect(e)),
        }
    }

    /// One registration attempt; why not on a failure worth retrying.
    async fn register(&self, mut client: Client) -> Result<Result<Session, String>, AgentError> {
        let url = self.url().to_string();
        let response = match within(CALL_TIMEOUT, client.register(self.request.clone())).await {
            Ok(response) => response,
            Err(status) if is_auth_failure(&status) => {
                return Err(AgentError::Unauthenticated {
                    url,
                    message: status.message().to_string(),
                })
            }
            Err(status)
                if matches!(
                    status.code(),
                    Code::FailedPrecondition | Code::InvalidArgument
                ) =>
            {
                return Err(AgentError::Refused {
                    url,
                    message: status.message().to_string(),
                })
            }
            Err(status) => return Ok(Err(describe(&status))),
        };
        let interval = match response.heartbeat_interval_ms {
            0 => DEFAULT_HEARTBEAT,
            ms => Duration::from_millis(u64::from(ms)).max(MIN_HEARTBEAT),
        };
        tracing::info!(
            "registered with {url} as worker {} ({}, engine {}, {:.3e} photons/s, heartbeat every {:.1} s)",
            response.worker_id,
            self.request.name,
            self.engine,
            self.request.photons_per_second,
            interval.as_secs_f64()
        );
        let forgotten = Arc::new(AtomicBool::new(false));
        let heartbeat = tokio::spawn(heartbeat(
            client.clone(),
            response.worker_id.clone(),
            interval,
            forgotten.clone(),
            url,
            self.stop.clone(),
        ));
        Ok(Ok(Session {
            client,
            worker_id: response.worker_id,
            forgotten,
            heartbeat,
        }))
    }
}

/// Sends a heartbeat every `interval` until the coordinator answers that it does not know
/// `worker_id` (then sets `forgotten` and ends). Failures are logged and the beat goes on: the
/// first as a warning, unless shutdown has been asked for (a coordinator that closes as this
/// worker leaves, as `demo`'s does, is no news).
async fn heartbeat(
    mut client: Client,
    worker_id: String,
    interval: Duration,
    forgotten: Arc<AtomicBool>,
    url: String,
    stop: Stop,
) {
    let mut ticker = tokio::time::interval(interval);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    ticker.tick().await;
    let mut failing = false;
    loop {
        ticker.tick().await;
        let request = HeartbeatRequest {
            worker_id: worker_id.clone(),
        };
        let known = match within(
            (interval * 4).clamp(Duration::from_secs(1), CALL_TIMEOUT),
            client.heartbeat(request),
        )
        .await
        {
            Ok(response) => response.known,
            Err(status) if status.code() == Code::NotFound => false,
            Err(status) => {
                if failing || stop.requested() {
                    tracing::debug!("heartbeat to {url} failed: {}", describe(&status));
                } else {
                    tracing::warn!("heartbeat to {url} failed: {}", describe(&status));
                }
                failing = true;
                continue;
            }
        };
        if failing {
            tracing::info!("heartbeats to {url} go through again");
            failing = false;
        }
        if !known {
            tracing::info!(
                "the coordinator at {url} no longer knows worker {worker_id}; registering again"
            );
            forgotten.store(true, Ordering::Relaxed);
            return;
        }
    }
}
