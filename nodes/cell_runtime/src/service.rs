//! Service replies that reach their client.
//!
//! A client may send its request as soon as it has matched this server's request reader and
//! response writer; this server may not yet have discovered the client's response reader,
//! and a response written before then is lost (the reply topic is volatile): a `ros2 service
//! call` made by a new process would wait for ever. So a reply waits, without holding up the
//! node, until the response writer has matched a reader of the client's participant, at most
//! [`REPLY_PATIENCE`] (rmw_cyclonedds's servers wait the same way).

use std::time::{Duration, Instant};

use ros2_client::{Gid, Message, RmwRequestId, Server};

/// How long a reply waits for its client's response reader to be matched before it is sent
/// anyway.
pub const REPLY_PATIENCE: Duration = Duration::from_secs(2);

/// A request as a server took it: its id and the client's request writer.
#[derive(Clone, Copy, Debug)]
pub struct Request {
    pub id: RmwRequestId,
    pub client: Gid,
}

/// Take the next request of `server` with who sent it.
pub async fn receive<Q: Message + 'static, R: Message + 'static>(
    server: &Server<Q, R>,
) -> Option<(Request, Q)> {
    match server.async_receive_request_with_info().await {
        Ok((id, request, info)) => Some((
            Request {
                id,
                client: info.publisher_gid(),
            },
            request,
        )),
        Err(_) => None,
    }
}

struct Pending<R> {
    server: usize,
    request: Request,
    response: R,
    give_up_at: Instant,
}

/// Replies waiting for their clients' readers, to servers numbered by the caller.
pub struct Replies<R> {
    pending: Vec<Pending<R>>,
}

impl<R> Default for Replies<R> {
    fn default() -> Self {
        Replies {
            pending: Vec::new(),
        }
    }
}

impl<R: Message + 'static> Replies<R> {
    /// Reply `response` to `request` of server number `server` when its client can hear it.
    pub fn push(&mut self, server: usize, request: Request, response: R) {
        self.pending.push(Pending {
            server,
            request,
            response,
            give_up_at: Instant::now() + REPLY_PATIENCE,
        });
    }

    /// Send the replies whose clients' readers are matched, or that waited long enough;
    /// `server(n)` is server number n. What went wrong, for the log (server number, words).
    pub fn send_ready<'s, Q: Message + 'static>(
        &mut self,
        server: impl Fn(usize) -> &'s Server<Q, R>,
    ) -> Vec<(usize, String)>
    where
        R: 's,
    {
        let now = Instant::now();
        let mut problems = Vec::new();
        let mut waiting = Vec::new();
        for p in self.pending.drain(..) {
            let to = server(p.server);
            let matched = to.response_reader_matched(p.request.client);
            if !matched && now < p.give_up_at {
                waiting.push(p);
                continue;
            }
            if !matched {
                problems.push((
                    p.server,
                    format!(
                        "the client's response reader was not matched after {} s: the reply may be lost",
                        REPLY_PATIENCE.as_secs_f64()
                    ),
                ));
            }
            if let Err(e) = to.send_response(p.request.id, p.response) {
                problems.push((p.server, format!("reply lost: {e:?}")));
            }
        }
        self.pending = waiting;
        problems
    }

    /// Whether no reply waits (the caller's loop may sleep longer).
    pub fn is_empty(&self) -> bool {
        self.pending.is_empty()
    }
}
