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

/// Answers waiting for their clients' response readers, whatever they are (a service's
/// replies, an action's goal, cancel and result answers): one waiting rule for all.
pub struct Waiting<T> {
    items: Vec<(Gid, T, Instant)>,
}

impl<T> Default for Waiting<T> {
    fn default() -> Self {
        Waiting { items: Vec::new() }
    }
}

impl<T> Waiting<T> {
    /// Hold `item` for the client whose request writer is `client`.
    pub fn push(&mut self, client: Gid, item: T) {
        self.items
            .push((client, item, Instant::now() + REPLY_PATIENCE));
    }

    /// Hand `send` every item whose client's reader `matched` says is matched (with `true`),
    /// or that has waited [`REPLY_PATIENCE`] (with `false`: it may be lost); keep the rest.
    pub fn release(&mut self, matched: impl Fn(Gid, &T) -> bool, mut send: impl FnMut(T, bool)) {
        let now = Instant::now();
        for (client, item, give_up_at) in std::mem::take(&mut self.items) {
            let heard = matched(client, &item);
            if heard || now >= give_up_at {
                send(item, heard);
            } else {
                self.items.push((client, item, give_up_at));
            }
        }
    }

    /// Whether nothing waits (the caller's loop may sleep longer).
    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }
}

/// Replies waiting for their clients' readers, to servers numbered by the caller.
pub struct Replies<R> {
    waiting: Waiting<(usize, RmwRequestId, R)>,
}

impl<R> Default for Replies<R> {
    fn default() -> Self {
        Replies {
            waiting: Waiting::default(),
        }
    }
}

impl<R: Message + 'static> Replies<R> {
    /// Reply `response` to `request` of server number `server` when its client can hear it.
    pub fn push(&mut self, server: usize, request: Request, response: R) {
        self.waiting
            .push(request.client, (server, request.id, response));
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
        let mut problems = Vec::new();
        self.waiting.release(
            |client, (index, _, _)| server(*index).response_reader_matched(client),
            |(index, id, response), heard| {
                if !heard {
                    problems.push((
                        index,
                        format!(
                            "the client's response reader was not matched after {} s: the reply may be lost",
                            REPLY_PATIENCE.as_secs_f64()
                        ),
                    ));
                }
                if let Err(e) = server(index).send_response(id, response) {
                    problems.push((index, format!("reply lost: {e:?}")));
                }
            },
        );
        problems
    }

    /// Whether no reply waits (the caller's loop may sleep longer).
    pub fn is_empty(&self) -> bool {
        self.waiting.is_empty()
    }
}
