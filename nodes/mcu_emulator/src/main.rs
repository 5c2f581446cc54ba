//! `mcu_emulator`: the cell's microcontroller on a pseudo-terminal or a Unix socket.
//!
//! It prints where it listens on its first line of standard output (`pty /dev/pts/N` or
//! `socket PATH`) and then runs until killed, paced by the monotonic clock (times `--speed`).
//! With `--edges FILE` every step edge is written to FILE as `clock,axes,negative` lines.

use std::fs::File;
use std::io::{BufWriter, ErrorKind, Read, Write};
use std::os::fd::{AsFd, OwnedFd};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Parser;
use mcu_emulator::{Crystal, Emulator, EmulatorOptions, LineFaults, Window};
use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use nix::sys::termios::{cfmakeraw, tcgetattr, tcsetattr, SetArg};

/// The polar cell's microcontroller, emulated: the firmware core behind a serial link.
#[derive(Parser, Debug)]
#[command(version)]
struct Args {
    /// Listen on a Unix socket at this path instead of a pseudo-terminal.
    #[arg(long)]
    socket: Option<PathBuf>,
    /// Run the MCU clock this many times faster than real time.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Step timer frequency (Hz).
    #[arg(long, default_value_t = 1e6)]
    timer_hz: f64,
    /// MCU clock at start (ticks).
    #[arg(long, default_value_t = 0)]
    offset_ticks: u64,
    /// Crystal rate error (ppm).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    rate_ppm: f64,
    /// Crystal drift (ppm per second).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    drift_ppm_per_s: f64,
    /// Probability per byte of a corrupted byte.
    #[arg(long, default_value_t = 0.0)]
    corrupt_rate: f64,
    /// Probability per byte of a dropped byte.
    #[arg(long, default_value_t = 0.0)]
    drop_rate: f64,
    /// Probability per byte of a duplicated byte.
    #[arg(long, default_value_t = 0.0)]
    duplicate_rate: f64,
    /// Seed of the line's faults.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Stall (stop answering) at this emulated time (s)...
    #[arg(long, requires = "stall_for")]
    stall_at: Option<f64>,
    /// ...for this long (s).
    #[arg(long, requires = "stall_at")]
    stall_for: Option<f64>,
    /// Power-cycle the MCU at this emulated time (s).
    #[arg(long)]
    reset_at: Option<f64>,
    /// Step position of each axis at power-up, `bed,arm,z`.
    #[arg(long, value_delimiter = ',', num_args = 3, default_values_t = [0, 0, 0])]
    initial_steps: Vec<i32>,
    /// Write every step edge to this file (`clock,axes,negative` per line).
    #[arg(long)]
    edges: Option<PathBuf>,
    /// The MCU link's longest wait for an acknowledgement (ms of wall time, whatever
    /// `--speed`: the host's round trip does not speed up with the emulated clock).
    #[arg(long, default_value_t = 50.0)]
    retransmit_timeout_ms: f64,
}

/// The serial side: a pty master, or the socket and its current connection.
enum Port {
    Pty {
        master: File,
        /// Held open so that the master never reads end-of-file between two openings of
        /// the slave by the host.
        _slave: OwnedFd,
    },
    Socket {
        listener: UnixListener,
        stream: Option<UnixStream>,
    },
}

fn rate(name: &str, p: f64) -> Result<f64> {
    if !(0.0..=1.0).contains(&p) {
        bail!("--{name} {p}: a probability must lie in 0..=1");
    }
    Ok(p)
}

/// The crystal's parameters, checked: an MCU counts whole ticks of a timer it reports as a
/// 32-bit rate, and a crystal runs forwards.
fn check_crystal(args: &Args) -> Result<()> {
    let hz = args.timer_hz;
    if !(hz.is_finite() && hz.fract() == 0.0 && (1000.0..=u32::MAX as f64).contains(&hz)) {
        bail!(
            "--timer-hz {hz}: must be a whole number of Hz from 1000 to {}",
            u32::MAX
        );
    }
    if args.offset_ticks > 1 << 62 {
        bail!(
            "--offset-ticks {}: at most 2^62, so that the clock does not wrap",
            args.offset_ticks
        );
    }
    if !(args.rate_ppm.is_finite() && args.rate_ppm.abs() <= 1e5) {
        bail!(
            "--rate-ppm {}: a crystal's rate error must lie within ±100000 ppm",
            args.rate_ppm
        );
    }
    if !(args.drift_ppm_per_s.is_finite() && args.drift_ppm_per_s.abs() <= 1e3) {
        bail!(
            "--drift-ppm-per-s {}: must lie within ±1000 ppm/s",
            args.drift_ppm_per_s
        );
    }
    Ok(())
}

fn main() -> Result<()> {
    let args = Args::parse();
    if !(args.speed > 0.0 && args.speed.is_finite()) {
        bail!("--speed {}: must be a positive number", args.speed);
    }
    check_crystal(&args)?;
    if !(args.retransmit_timeout_ms.is_finite()
        && (0.1..=10_000.0).contains(&args.retransmit_timeout_ms))
    {
        bail!(
            "--retransmit-timeout-ms {}: must lie within 0.1..=10000",
            args.retransmit_timeout_ms
        );
    }
    let options = EmulatorOptions {
        crystal: Crystal {
            timer_hz: args.timer_hz,
            offset_ticks: args.offset_ticks,
            rate_ppm: args.rate_ppm,
            drift_ppm_per_s: args.drift_ppm_per_s,
        },
        faults: LineFaults {
            corrupt: rate("corrupt-rate", args.corrupt_rate)?,
            drop: rate("drop-rate", args.drop_rate)?,
            duplicate: rate("duplicate-rate", args.duplicate_rate)?,
        },
        seed: args.seed,
        stall: args
            .stall_at
            .zip(args.stall_for)
            .map(|(at_s, for_s)| Window { at_s, for_s }),
        reset_at_s: args.reset_at,
        initial_steps: [
            args.initial_steps[0],
            args.initial_steps[1],
            args.initial_steps[2],
        ],
        retransmit_timeout_s: args.retransmit_timeout_ms * 1e-3 * args.speed,
        ..EmulatorOptions::default()
    };
    let mut port = open_port(&args)?;
    let mut edges = match &args.edges {
        Some(path) => Some(BufWriter::new(
            File::create(path).with_context(|| format!("creating {}", path.display()))?,
        )),
        None => None,
    };
    let mut emulator = Emulator::new(options);
    let start = Instant::now();
    let mut input = [0u8; 4096];
    let mut output = Vec::new();
    let mut outbox = Outbox::default();
    let mut dropped_reported = 0;
    let mut last_drop_report = None;
    loop {
        let host_s = start.elapsed().as_secs_f64() * args.speed;
        let received = read_some(&mut port, &mut input)?;
        if received > 0 {
            emulator.receive(&input[..received], host_s);
        }
        output.clear();
        let mut write_error = None;
        emulator.run_until(
            host_s,
            &mut |edge| {
                if let Some(w) = edges.as_mut() {
                    if let Err(e) = writeln!(w, "{},{},{}", edge.clock, edge.axes, edge.negative) {
                        write_error.get_or_insert(e);
                    }
                }
            },
            &mut output,
        );
        if let Some(e) = write_error {
            return Err(e).context("writing the edge file");
        }
        if let Some(w) = edges.as_mut() {
            w.flush().context("writing the edge file")?;
        }
        outbox.push(&output);
        send(&mut port, &mut outbox)?;
        // (Said at most once a second: a host that stopped reading would fill the log.)
        if outbox.dropped_bytes > dropped_reported
            && last_drop_report.is_none_or(|at: Instant| at.elapsed() >= Duration::from_secs(1))
        {
            last_drop_report = Some(Instant::now());
            eprintln!(
                "mcu_emulator: the host reads nothing: {} bytes for it dropped (more than {} waiting)",
                outbox.dropped_bytes, OUTBOX_BYTES
            );
            dropped_reported = outbox.dropped_bytes;
        }
        wait_readable(&port, Duration::from_millis(1))?;
    }
}

/// Removes what an earlier emulator left at `path`: only a socket nobody listens on. Any
/// other file there is the user's, and a live socket another emulator's.
fn remove_stale_socket(path: &std::path::Path) -> Result<()> {
    use std::os::unix::fs::FileTypeExt;
    let Ok(metadata) = std::fs::symlink_metadata(path) else {
        return Ok(());
    };
    if !metadata.file_type().is_socket() {
        bail!(
            "--socket {}: a file that is not a socket is there; not removing it",
            path.display()
        );
    }
    if UnixStream::connect(path).is_ok() {
        bail!(
            "--socket {}: another process listens there (an emulator already running?)",
            path.display()
        );
    }
    std::fs::remove_file(path)
        .with_context(|| format!("removing the stale socket {}", path.display()))
}

fn open_port(args: &Args) -> Result<Port> {
    let mut stdout = std::io::stdout().lock();
    let port = match &args.socket {
        Some(path) => {
            remove_stale_socket(path)?;
            let listener = UnixListener::bind(path)
                .with_context(|| format!("binding the socket {}", path.display()))?;
            listener.set_nonblocking(true)?;
            writeln!(stdout, "socket {}", path.display())?;
            Port::Socket {
                listener,
                stream: None,
            }
        }
        None => {
            let pty = nix::pty::openpty(None, None).context("opening a pseudo-terminal")?;
            // Raw: the line carries binary frames, no echo, no line discipline.
            for fd in [pty.master.as_fd(), pty.slave.as_fd()] {
                let mut termios = tcgetattr(fd)?;
                cfmakeraw(&mut termios);
                tcsetattr(fd, SetArg::TCSANOW, &termios)?;
            }
            let path = nix::unistd::ttyname(pty.slave.as_fd())?;
            let master = File::from(pty.master);
            set_nonblocking(&master)?;
            writeln!(stdout, "pty {}", path.display())?;
            Port::Pty {
                master,
                _slave: pty.slave,
            }
        }
    };
    stdout.flush()?;
    Ok(port)
}

fn set_nonblocking(file: &impl AsFd) -> Result<()> {
    use nix::fcntl::{fcntl, FcntlArg, OFlag};
    let flags = OFlag::from_bits_truncate(fcntl(file.as_fd(), FcntlArg::F_GETFL)?);
    fcntl(file.as_fd(), FcntlArg::F_SETFL(flags | OFlag::O_NONBLOCK))?;
    Ok(())
}

/// Whatever has arrived (0 if nothing); a socket peer that left is replaced by the next.
fn read_some(port: &mut Port, buf: &mut [u8]) -> Result<usize> {
    match port {
        Port::Pty { master, .. } => match master.read(buf) {
            Ok(n) => Ok(n),
            Err(e) if e.kind() == ErrorKind::WouldBlock => Ok(0),
            // EIO: no process has the slave open at the moment.
            Err(e) if e.raw_os_error() == Some(libc_eio()) => Ok(0),
            Err(e) => Err(e).context("reading the pseudo-terminal"),
        },
        Port::Socket { listener, stream } => {
            if stream.is_none() {
                match listener.accept() {
                    Ok((s, _)) => {
                        s.set_nonblocking(true)?;
                        *stream = Some(s);
                    }
                    Err(e) if e.kind() == ErrorKind::WouldBlock => return Ok(0),
                    Err(e) => return Err(e).context("accepting on the socket"),
                }
            }
            let s = stream.as_mut().expect("connected");
            match s.read(buf) {
                Ok(0) => {
                    *stream = None; // the host hung up
                    Ok(0)
                }
                Ok(n) => Ok(n),
                Err(e) if e.kind() == ErrorKind::WouldBlock => Ok(0),
                Err(e) if e.kind() == ErrorKind::ConnectionReset => {
                    *stream = None;
                    Ok(0)
                }
                Err(e) => Err(e).context("reading the socket"),
            }
        }
    }
}

fn libc_eio() -> i32 {
    nix::errno::Errno::EIO as i32
}

/// How much output may wait for a host that reads slowly (a tty's or socket's buffer holds
/// about this much): past it, the host has stopped reading.
const OUTBOX_BYTES: usize = 64 * 1024;

/// Output for the host that the line has not taken yet. A host that reads late gets every
/// byte, in order, as from a USB CDC port (a non-blocking write takes part of a frame when the
/// kernel's buffer is nearly full; the rest used to be dropped, a cut frame the host saw as
/// line damage). Only past [`OUTBOX_BYTES`] is new output dropped, and counted: a pass's
/// output whole (its frames), never part of a frame.
#[derive(Default)]
struct Outbox {
    pending: Vec<u8>,
    dropped_bytes: u64,
}

impl Outbox {
    fn push(&mut self, bytes: &[u8]) {
        if self.pending.len() + bytes.len() <= OUTBOX_BYTES {
            self.pending.extend_from_slice(bytes);
        } else {
            self.dropped_bytes += bytes.len() as u64;
        }
    }

    /// Write what `line` takes now. `Ok(false)`: nobody is there to read (the bytes are lost,
    /// as on a line nobody listens to).
    fn write_to(&mut self, line: &mut impl Write) -> std::io::Result<bool> {
        let mut written = 0;
        let result = loop {
            if written == self.pending.len() {
                break Ok(true);
            }
            match line.write(&self.pending[written..]) {
                Ok(0) => break Ok(true),
                Ok(n) => written += n,
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) if e.kind() == ErrorKind::WouldBlock => break Ok(true),
                Err(e)
                    if matches!(e.kind(), ErrorKind::BrokenPipe | ErrorKind::ConnectionReset)
                        || e.raw_os_error() == Some(libc_eio()) =>
                {
                    written = self.pending.len();
                    break Ok(false);
                }
                Err(e) => break Err(e),
            }
        };
        self.pending.drain(..written);
        result
    }
}

/// Send what waits for the host; a socket peer that left is forgotten (what waited for it
/// with it), and with nobody connected the bytes are lost, as on a real line.
fn send(port: &mut Port, outbox: &mut Outbox) -> Result<()> {
    match port {
        Port::Pty { master, .. } => {
            outbox.write_to(master).context("writing to the host")?;
        }
        Port::Socket { stream, .. } => match stream {
            Some(s) => {
                if !outbox.write_to(s).context("writing to the host")? {
                    *stream = None;
                }
            }
            None => outbox.pending.clear(),
        },
    }
    Ok(())
}

/// Sleep until input arrives or `timeout` passes.
fn wait_readable(port: &Port, timeout: Duration) -> Result<()> {
    let fd = match port {
        Port::Pty { master, .. } => master.as_fd(),
        Port::Socket {
            stream: Some(s), ..
        } => s.as_fd(),
        Port::Socket { listener, .. } => listener.as_fd(),
    };
    let ms = timeout.as_millis().min(u16::MAX as u128) as u16;
    let mut fds = [PollFd::new(fd, PollFlags::POLLIN)];
    match poll(&mut fds, PollTimeout::from(ms)) {
        Ok(_) | Err(nix::errno::Errno::EINTR) => Ok(()),
        Err(e) => Err(e).context("waiting for input"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A line whose buffer takes `room` bytes per pass, then would block; or is gone.
    struct SlowLine {
        received: Vec<u8>,
        room: usize,
        left: usize,
        gone: bool,
    }

    impl SlowLine {
        fn new(room: usize) -> SlowLine {
            SlowLine {
                received: Vec::new(),
                room,
                left: room,
                gone: false,
            }
        }
        fn next_pass(&mut self) {
            self.left = self.room;
        }
    }

    impl Write for SlowLine {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            if self.gone {
                return Err(ErrorKind::BrokenPipe.into());
            }
            if self.left == 0 {
                return Err(ErrorKind::WouldBlock.into());
            }
            let n = bytes.len().min(self.left).min(7);
            self.left -= n;
            self.received.extend_from_slice(&bytes[..n]);
            Ok(n)
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn a_host_that_reads_slowly_gets_every_byte_in_order() {
        let mut outbox = Outbox::default();
        let mut line = SlowLine::new(100);
        let mut sent = Vec::new();
        for pass in 0..50u32 {
            let frame: Vec<u8> = (0..37).map(|i| (pass * 37 + i) as u8).collect();
            sent.extend_from_slice(&frame);
            outbox.push(&frame);
            assert!(outbox.write_to(&mut line).unwrap());
            line.next_pass();
        }
        while !outbox.pending.is_empty() {
            assert!(outbox.write_to(&mut line).unwrap());
            line.next_pass();
        }
        assert_eq!(line.received, sent);
        assert_eq!(outbox.dropped_bytes, 0);
    }

    #[test]
    fn a_host_that_stopped_reading_loses_only_what_overflows_and_it_is_counted() {
        let mut outbox = Outbox::default();
        let mut line = SlowLine::new(0);
        let frame = vec![0x7e; 1000];
        for _ in 0..100 {
            outbox.push(&frame);
            assert!(outbox.write_to(&mut line).unwrap());
        }
        // 65 whole frames wait; the other 35 are dropped whole.
        assert_eq!(outbox.pending.len(), 65_000);
        assert_eq!(outbox.dropped_bytes, 35_000);
        // The line goes: what waited is lost with it, and the caller is told.
        line.gone = true;
        assert!(!outbox.write_to(&mut line).unwrap());
        assert!(outbox.pending.is_empty());
    }
}
