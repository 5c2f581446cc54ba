//! The MCU's bytes stamped when they arrive, by a thread that waits on the line.
//!
//! The bridge's loop looks at its line every 5 ms; bytes read then looked as old as the look,
//! and a clock reply's round trip seemed the loop's period long. Clock sync places the MCU's
//! clock at the middle of the round trip, so it put it 2.5 ms late on average (3.4 ms on the
//! simulated line of the clock-sync test, 0.45 ms with 1 ms looks). A thread blocked in
//! `poll` takes each burst as it comes and notes the instant; the loop hands both on.

use std::io::{ErrorKind, Read};
use std::os::fd::AsFd;
use std::os::unix::net::UnixStream;
use std::sync::mpsc::{channel, Receiver, Sender, TryRecvError};
use std::thread::JoinHandle;
use std::time::Instant;

use nix::poll::{poll, PollFd, PollFlags, PollTimeout};

/// What the thread saw.
enum Arrival {
    Bytes(Instant, Vec<u8>),
    /// The other end closed the line.
    Closed,
    Failed(std::io::Error),
}

/// A line's own readable end (a duplicate of the device's descriptor).
pub trait ReadEnd: Read + AsFd + Send + 'static {}
impl<T: Read + AsFd + Send + 'static> ReadEnd for T {}

/// How the line ended, once its bytes before that were taken.
#[derive(Debug)]
pub enum LineEnd {
    Closed,
    Failed(std::io::Error),
}

/// Bytes as they arrived, each burst with its instant. Dropped, it stops its thread and
/// waits for it: the thread's duplicate of the line must not outlive it (the next session
/// on the same tty shares its input, and a dying reader would take the bytes meant for it).
pub struct LineReader {
    arrivals: Receiver<Arrival>,
    /// Closed to wake the thread and make it stop.
    wake: Option<UnixStream>,
    thread: Option<JoinHandle<()>>,
    ended: bool,
}

impl LineReader {
    /// Read `end` (non-blocking, as the device is) on a thread of its own.
    pub fn start(end: impl ReadEnd, name: &str) -> std::io::Result<LineReader> {
        let (tx, arrivals) = channel();
        let (wake, woken) = UnixStream::pair()?;
        let thread = std::thread::Builder::new()
            .name(format!("read {name}"))
            .spawn(move || read_line(end, &tx, &woken))?;
        Ok(LineReader {
            arrivals,
            wake: Some(wake),
            thread: Some(thread),
            ended: false,
        })
    }

    /// Every burst that has arrived: its bytes appended to `into`, and (end in `into`,
    /// instant) for each. After the last bytes, how the line ended (once).
    pub fn take(
        &mut self,
        into: &mut Vec<u8>,
        bursts: &mut Vec<(usize, Instant)>,
    ) -> Result<(), LineEnd> {
        loop {
            match self.arrivals.try_recv() {
                Ok(Arrival::Bytes(at, bytes)) => {
                    into.extend_from_slice(&bytes);
                    bursts.push((into.len(), at));
                }
                Ok(Arrival::Closed) => {
                    self.ended = true;
                    return Err(LineEnd::Closed);
                }
                Ok(Arrival::Failed(e)) => {
                    self.ended = true;
                    return Err(LineEnd::Failed(e));
                }
                Err(TryRecvError::Empty) => return Ok(()),
                // The thread is gone after saying how the line ended.
                Err(TryRecvError::Disconnected) if self.ended => return Err(LineEnd::Closed),
                Err(TryRecvError::Disconnected) => {
                    self.ended = true;
                    return Err(LineEnd::Failed(std::io::Error::other(
                        "the line's reader stopped",
                    )));
                }
            }
        }
    }
}

impl Drop for LineReader {
    fn drop(&mut self) {
        // Its end of the pair becomes readable (end of file): the thread returns at once.
        drop(self.wake.take());
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

fn read_line(mut end: impl ReadEnd, tx: &Sender<Arrival>, woken: &UnixStream) {
    let mut buf = [0u8; 4096];
    loop {
        let mut fds = [
            PollFd::new(end.as_fd(), PollFlags::POLLIN),
            PollFd::new(woken.as_fd(), PollFlags::POLLIN),
        ];
        match poll(&mut fds, PollTimeout::NONE) {
            Ok(0) | Err(nix::errno::Errno::EINTR) => continue,
            Ok(_) => {}
            Err(e) => {
                let _ = tx.send(Arrival::Failed(e.into()));
                return;
            }
        }
        if fds[1].any().unwrap_or(true) {
            return; // the reader was dropped
        }
        // The instant `poll` woke: the burst's arrival (its reads follow at once).
        let woke = Instant::now();
        loop {
            let ended = match end.read(&mut buf) {
                Ok(0) => Arrival::Closed,
                Ok(n) => {
                    if tx.send(Arrival::Bytes(woke, buf[..n].to_vec())).is_err() {
                        return; // nobody takes them any more
                    }
                    continue;
                }
                Err(e) if e.kind() == ErrorKind::WouldBlock => break,
                Err(e) if e.kind() == ErrorKind::Interrupted => continue,
                // A pseudo-terminal whose other side has gone.
                Err(e) if e.raw_os_error() == Some(nix::libc::EIO) => Arrival::Closed,
                Err(e) => Arrival::Failed(e),
            };
            let _ = tx.send(ended);
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;
    use std::os::unix::net::UnixStream;
    use std::time::Duration;

    fn reader_of_pair() -> (LineReader, UnixStream) {
        let (ours, theirs) = UnixStream::pair().unwrap();
        ours.set_nonblocking(true).unwrap();
        (LineReader::start(ours, "pair").unwrap(), theirs)
    }

    /// Bytes taken long after they came still carry when they came.
    #[test]
    fn bytes_carry_the_instant_they_arrived_not_when_they_were_taken() {
        let (mut reader, mut mcu) = reader_of_pair();
        let mut sent = Vec::new();
        for burst in [&b"\x00frame one\x00"[..], b"frame two\x00"] {
            mcu.write_all(burst).unwrap();
            sent.push((Instant::now(), burst.len()));
            std::thread::sleep(Duration::from_millis(30));
        }
        let (mut into, mut bursts) = (Vec::new(), Vec::new());
        reader.take(&mut into, &mut bursts).unwrap();
        assert_eq!(into, b"\x00frame one\x00frame two\x00");
        assert_eq!(bursts.len(), 2, "{bursts:?}");
        let mut end = 0;
        for ((taken_end, at), (written_at, len)) in bursts.iter().zip(&sent) {
            end += len;
            assert_eq!(*taken_end, end);
            // Within a few ms of the write (a loaded machine's scheduling), where the take
            // came 30–60 ms after it.
            let late = at.duration_since(*written_at);
            assert!(late < Duration::from_millis(10), "stamped {late:?} late");
        }
    }

    /// Dropped, the reader's thread is gone with it, its duplicate of the line closed: the
    /// other end sees the line closed at once.
    #[test]
    fn a_dropped_reader_lets_go_of_the_line_at_once() {
        let (reader, mcu) = reader_of_pair();
        let dropped = Instant::now();
        drop(reader);
        assert!(dropped.elapsed() < Duration::from_millis(20));
        // Both ends of `ours` are closed now (the pair's and the thread's duplicate).
        let mut byte = [0u8; 1];
        mcu.set_read_timeout(Some(Duration::from_millis(100)))
            .unwrap();
        assert_eq!((&mcu).read(&mut byte).unwrap(), 0, "the line is closed");
    }

    /// The other end's close comes after every byte sent before it, once.
    #[test]
    fn a_closed_line_ends_after_its_last_bytes() {
        let (mut reader, mut mcu) = reader_of_pair();
        mcu.write_all(b"last words\x00").unwrap();
        drop(mcu);
        std::thread::sleep(Duration::from_millis(30));
        let (mut into, mut bursts) = (Vec::new(), Vec::new());
        assert!(matches!(
            reader.take(&mut into, &mut bursts),
            Err(LineEnd::Closed)
        ));
        assert_eq!(into, b"last words\x00");
        assert!(matches!(
            reader.take(&mut into, &mut bursts),
            Err(LineEnd::Closed)
        ));
    }
}
