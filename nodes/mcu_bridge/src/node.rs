//! The `mcu_bridge` node: a microcontroller as the cell's machine on the ROS graph.
//!
//! It opens the MCU's serial line (parameter `device`: a tty such as `/dev/ttyACM0`, a
//! pseudo-terminal's path, or `unix:/path` for a Unix socket), and serves exactly what the
//! virtual executor serves — `/joint_states`, `/tf`, plan credit, `/diagnostics`, the `/cell/*`
//! services — through the same loop ([`cell_machine::node`]), with an [`McuMachine`] as the
//! machine. The positions it publishes are the MCU's reported step counts, stamped with the
//! instant the MCU measured them (its clock mapped to ours by the clock synchronisation).
//!
//! Times: the node's machine clock is the monotonic clock times `speed`, as for the executor;
//! an emulated MCU run `speed`× faster keeps in step with it. The host's timeouts (the MCU's
//! watchdog, the host's silence bound, retransmits, the lead before a plan's first segment)
//! are parameters in wall seconds, scaled to
//! machine time by `speed`, so that a loaded test machine at `--speed 10` is not mistaken for
//! a dead link.

use std::fs::{File, OpenOptions};
use std::io::{ErrorKind, Read, Write};
use std::os::fd::AsFd;
use std::os::unix::fs::OpenOptionsExt;
use std::os::unix::net::UnixStream;

use anyhow::Context as _;
use cell_machine::node::{MachineParams, Request, Status};
use cell_runtime::{CellNode, LogLevel, ParamSpec, ParamValue};
use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use nix::sys::termios::{cfmakeraw, cfsetspeed, tcgetattr, tcsetattr, BaudRate, SetArg};
use tokio::sync::{mpsc, watch};

use crate::line_reader::{LineEnd, LineReader};
use crate::machine::{McuLink, McuMachine};
use crate::screw_line::{CommandTemplate, ScrewLine};
use crate::screw_port::WithScrewLine;
use crate::session::{McuSession, SessionOptions};

/// Default node name.
pub const NODE_NAME: &str = "mcu_bridge";

/// The bridge's default `tick_period_s`: it reads and writes its line on every look.
pub const BRIDGE_TICK_PERIOD_S: f64 = 0.005;

/// The machine node's parameters and the bridge's own.
pub fn param_specs() -> Vec<ParamSpec> {
    let mut specs = cell_machine::node::param_specs(BRIDGE_TICK_PERIOD_S);
    specs.extend([
        ParamSpec::new(
            "device",
            ParamValue::String(String::new()),
            "the MCU's serial line: a tty (/dev/ttyACM0), a pseudo-terminal's path, or unix:/path",
        ),
        ParamSpec::new(
            "open_timeout_s",
            ParamValue::Double(5.0),
            "wait this long for the device to appear (wall seconds)",
        )
        .range(0.0, 600.0),
        ParamSpec::new(
            "baud",
            ParamValue::Integer(921_600),
            "line speed of a tty: the firmware's UART0 runs at 921600 (ignored by USB CDC and pseudo-terminals)",
        )
        .range(1200.0, 4e6),
        ParamSpec::new(
            "lead_s",
            ParamValue::Double(0.25),
            "time between a plan's first segment and its start on the MCU, for the first frames to arrive (wall seconds)",
        )
        .range(0.01, 10.0),
        ParamSpec::new(
            "state_period_s",
            ParamValue::Double(0.01),
            "machine time between the MCU's state reports (the positions published)",
        )
        .range(0.001, 1.0),
        ParamSpec::new(
            "clock_query_period_s",
            ParamValue::Double(0.1),
            "machine time between clock queries while the clock fit settles (its first 100 samples)",
        )
        .range(0.001, 10.0),
        ParamSpec::new(
            "clock_query_settled_period_s",
            ParamValue::Double(0.5),
            "machine time between clock queries once the fit has settled (at most a quarter of host_timeout_s: the queries are the MCU watchdog's keep-alive)",
        )
        .range(0.001, 10.0),
        ParamSpec::new(
            "host_timeout_s",
            ParamValue::Double(1.0),
            "the MCU faults when the host is silent this long (wall seconds)",
        )
        .range(0.05, 60.0),
        ParamSpec::new(
            "silence_s",
            ParamValue::Double(0.25),
            "the host faults when the MCU is silent this long (wall seconds)",
        )
        .range(0.01, 60.0),
        ParamSpec::new(
            "answer_timeout_s",
            ParamValue::Double(5.0),
            "the host faults when the MCU is not ready (linked, identified, clock fitted, reporting) this long after the session began (wall seconds)",
        )
        .range(0.1, 600.0),
        ParamSpec::new(
            "screw_port",
            ParamValue::String(String::new()),
            "the screw's servo amplifier on an ASCII serial line (a tty or pseudo-terminal path); empty: the MCU drives the screw",
        ),
        ParamSpec::new(
            "screw_port_baud",
            ParamValue::Integer(9600),
            "line speed of the screw's serial line",
        )
        .range(1200.0, 4e6),
        ParamSpec::new(
            "screw_port_framing",
            ParamValue::String("8N1".into()),
            "data bits (5-8), parity (N, E or O) and stop bits (1 or 2) of the screw's serial line",
        ),
        ParamSpec::new(
            "screw_command_template",
            ParamValue::String(crate::screw_line::DEFAULT_TEMPLATE.into()),
            "one screw command line: {rpm}, {rpm:.N}, {millirpm}, {pin} or {pin:OPEN/CLOSED}; \\r \\n \\t \\xHH for control bytes",
        ),
        ParamSpec::new(
            "screw_max_rate_hz",
            ParamValue::Double(10.0),
            "most screw command lines a second (machine time); each holds the exact average of the commanded rpm over its interval",
        )
        .range(0.01, 1000.0),
        ParamSpec::new(
            "pack_s",
            ParamValue::Double(0.1),
            "machine time continuing segments and screw commands may wait for more to fill their frame (0: every write sends what is ready)",
        )
        .range(0.0, 0.5),
        ParamSpec::new(
            "retransmit_timeout_s",
            ParamValue::Double(0.05),
            "an unacknowledged frame is sent again after this long (wall seconds)",
        )
        .range(0.001, 10.0),
    ]);
    specs
}

/// The MCU's serial line: a tty or pseudo-terminal, or a Unix socket.
pub enum Device {
    Tty(File),
    Socket(UnixStream),
}

/// What the serial line did wrong.
#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    #[error("{device}: {source}")]
    Io {
        device: String,
        source: std::io::Error,
    },
    #[error("{device}: the other end closed the line")]
    Closed { device: String },
    #[error("{device}: the MCU does not take what is written (blocked for 100 ms)")]
    Blocked { device: String },
}

/// Character framing of a serial line: data bits, parity, stop bits (`8N1`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Framing {
    pub data_bits: u8,
    pub parity: Parity,
    pub stop_bits: u8,
}

impl Framing {
    /// Bits on the wire for one character: a start bit, the data, parity, the stop bits.
    pub fn bits_per_character(&self) -> u32 {
        1 + self.data_bits as u32 + u32::from(self.parity != Parity::None) + self.stop_bits as u32
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Parity {
    None,
    Even,
    Odd,
}

impl Framing {
    /// Eight data bits, no parity, one stop bit: the MCU's line.
    pub const EIGHT_N_ONE: Framing = Framing {
        data_bits: 8,
        parity: Parity::None,
        stop_bits: 1,
    };
}

impl std::str::FromStr for Framing {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Framing> {
        let bad = || {
            anyhow::anyhow!(
                "serial framing {s:?}: want data bits 5-8, parity N, E or O, stop bits 1 or 2 (as 8N1 or 7E2)"
            )
        };
        let b = s.as_bytes();
        if b.len() != 3 {
            return Err(bad());
        }
        let data_bits = match b[0] {
            b'5'..=b'8' => b[0] - b'0',
            _ => return Err(bad()),
        };
        let parity = match b[1].to_ascii_uppercase() {
            b'N' => Parity::None,
            b'E' => Parity::Even,
            b'O' => Parity::Odd,
            _ => return Err(bad()),
        };
        let stop_bits = match b[2] {
            b'1' | b'2' => b[2] - b'0',
            _ => return Err(bad()),
        };
        Ok(Framing {
            data_bits,
            parity,
            stop_bits,
        })
    }
}

impl Device {
    /// Open `spec`: `unix:/path` or the path of a tty, raw, at `baud`, 8N1.
    pub fn open(spec: &str, baud: u32) -> anyhow::Result<(Device, String)> {
        Device::open_framed(spec, baud, Framing::EIGHT_N_ONE).context("the MCU's line")
    }

    /// Open `spec` as [`Device::open`] does, with the tty's characters framed as `framing`.
    pub fn open_framed(
        spec: &str,
        baud: u32,
        framing: Framing,
    ) -> anyhow::Result<(Device, String)> {
        if let Some(path) = spec.strip_prefix("unix:") {
            let stream = UnixStream::connect(path)
                .with_context(|| format!("connecting to the socket {path}"))?;
            stream.set_nonblocking(true)?;
            return Ok((Device::Socket(stream), spec.to_string()));
        }
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(nix::libc::O_NOCTTY | nix::libc::O_NONBLOCK)
            .open(spec)
            .with_context(|| format!("opening the serial line {spec}"))?;
        // Raw: binary frames, no echo, no line discipline.
        let mut termios = tcgetattr(file.as_fd()).with_context(|| format!("{spec}: not a tty"))?;
        cfmakeraw(&mut termios);
        cfsetspeed(&mut termios, baud_rate(baud)?)?;
        use nix::sys::termios::ControlFlags as C;
        termios.control_flags &= !(C::CSIZE | C::PARENB | C::PARODD | C::CSTOPB);
        termios.control_flags |= match framing.data_bits {
            5 => C::CS5,
            6 => C::CS6,
            7 => C::CS7,
            _ => C::CS8,
        };
        match framing.parity {
            Parity::None => {}
            Parity::Even => termios.control_flags |= C::PARENB,
            Parity::Odd => termios.control_flags |= C::PARENB | C::PARODD,
        }
        if framing.stop_bits == 2 {
            termios.control_flags |= C::CSTOPB;
        }
        tcsetattr(file.as_fd(), SetArg::TCSANOW, &termios)?;
        Ok((Device::Tty(file), spec.to_string()))
    }
}

fn baud_rate(baud: u32) -> anyhow::Result<BaudRate> {
    Ok(match baud {
        1200 => BaudRate::B1200,
        2400 => BaudRate::B2400,
        4800 => BaudRate::B4800,
        9600 => BaudRate::B9600,
        19200 => BaudRate::B19200,
        38400 => BaudRate::B38400,
        57600 => BaudRate::B57600,
        115_200 => BaudRate::B115200,
        230_400 => BaudRate::B230400,
        460_800 => BaudRate::B460800,
        921_600 => BaudRate::B921600,
        1_000_000 => BaudRate::B1000000,
        2_000_000 => BaudRate::B2000000,
        other => anyhow::bail!(
            "baud {other} is not one of 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, \
             460800, 921600, 1000000, 2000000"
        ),
    })
}

/// The device with its name, for messages.
pub struct SerialLink {
    device: Device,
    name: String,
    /// With [`SerialLink::stamping_arrivals`]: the bytes as they came.
    reader: Option<LineReader>,
    /// The wall instant of machine time 0 and the machine's speed (machine seconds per wall
    /// second), to place arrivals on the machine's clock.
    clock: Option<(std::time::Instant, f64)>,
}

impl SerialLink {
    pub fn new(device: Device, name: String) -> SerialLink {
        SerialLink {
            device,
            name,
            reader: None,
            clock: None,
        }
    }

    /// Read on a thread that notes when bytes arrive (see [`crate::line_reader`]): the MCU's
    /// line, whose clock replies clock sync times. The machine's clock comes with
    /// [`McuLink::clock_started`].
    pub fn stamping_arrivals(mut self) -> anyhow::Result<SerialLink> {
        let end: Box<dyn ReadFd> = match &self.device {
            Device::Tty(f) => Box::new(f.try_clone()?),
            Device::Socket(s) => Box::new(s.try_clone()?),
        };
        let reader = LineReader::start(end, &self.name)
            .with_context(|| format!("{}: starting its reader", self.name))?;
        self.reader = Some(reader);
        Ok(self)
    }

    fn io(&self, source: std::io::Error) -> DeviceError {
        DeviceError::Io {
            device: self.name.clone(),
            source,
        }
    }

    fn stream(&mut self) -> &mut dyn ReadWrite {
        match &mut self.device {
            Device::Tty(f) => f,
            Device::Socket(s) => s,
        }
    }

    fn wait_writable(&self) -> bool {
        let fd = match &self.device {
            Device::Tty(f) => f.as_fd(),
            Device::Socket(s) => s.as_fd(),
        };
        let mut fds = [PollFd::new(fd, PollFlags::POLLOUT)];
        matches!(poll(&mut fds, PollTimeout::from(100u8)), Ok(n) if n > 0)
    }
}

trait ReadWrite: Read + Write {}
impl<T: Read + Write> ReadWrite for T {}

/// A device's duplicate for the reader thread.
trait ReadFd: Read + AsFd + Send {}
impl<T: Read + AsFd + Send> ReadFd for T {}

impl McuLink for SerialLink {
    type Error = DeviceError;

    fn read_arrivals(
        &mut self,
        now_ns: i64,
        into: &mut Vec<u8>,
        arrivals: &mut Vec<(usize, i64)>,
    ) -> Result<(), DeviceError> {
        let Some(reader) = &mut self.reader else {
            let result = self.read(now_ns, into);
            arrivals.push((into.len(), now_ns));
            return result;
        };
        let mut bursts = Vec::new();
        let result = reader.take(into, &mut bursts);
        // On the machine's clock (before it started: as now, the only time there is).
        arrivals.extend(bursts.into_iter().map(|(end, at)| match self.clock {
            Some((origin, speed)) => (
                end,
                (at.saturating_duration_since(origin).as_nanos() as f64 * speed) as i64,
            ),
            None => (end, now_ns),
        }));
        result.map_err(|end| match end {
            LineEnd::Closed => DeviceError::Closed {
                device: self.name.clone(),
            },
            LineEnd::Failed(source) => self.io(source),
        })
    }

    fn clock_started(&mut self, origin: std::time::Instant, speed: f64) {
        self.clock = Some((origin, speed));
    }

    fn read(&mut self, now_ns: i64, into: &mut Vec<u8>) -> Result<(), DeviceError> {
        if self.reader.is_some() {
            return self.read_arrivals(now_ns, into, &mut Vec::new());
        }
        let mut buf = [0u8; 4096];
        loop {
            match self.stream().read(&mut buf) {
                Ok(0) => {
                    return Err(DeviceError::Closed {
                        device: self.name.clone(),
                    })
                }
                Ok(n) => into.extend_from_slice(&buf[..n]),
                Err(e) if e.kind() == ErrorKind::WouldBlock => return Ok(()),
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                // A pseudo-terminal whose other side has gone.
                Err(e) if e.raw_os_error() == Some(nix::libc::EIO) => {
                    return Err(DeviceError::Closed {
                        device: self.name.clone(),
                    })
                }
                Err(e) => return Err(self.io(e)),
            }
        }
    }

    fn write(&mut self, _now_ns: i64, mut bytes: &[u8]) -> Result<(), DeviceError> {
        while !bytes.is_empty() {
            match self.stream().write(bytes) {
                Ok(n) => bytes = &bytes[n..],
                Err(e) if e.kind() == ErrorKind::WouldBlock => {
                    if !self.wait_writable() {
                        return Err(DeviceError::Blocked {
                            device: self.name.clone(),
                        });
                    }
                }
                Err(e) if e.kind() == ErrorKind::Interrupted => {}
                Err(e) => return Err(self.io(e)),
            }
        }
        Ok(())
    }
}

/// The screw's amplifier on a serial line: each command written whole.
impl crate::screw_port::LinePort for SerialLink {
    type Error = DeviceError;
    fn send(&mut self, now_ns: i64, text: &str) -> Result<(), DeviceError> {
        McuLink::write(self, now_ns, text.as_bytes())
    }
}

/// The session the parameters describe, its timeouts in machine time at `params.speed`.
pub fn session_options(node: &CellNode, params: &MachineParams) -> SessionOptions {
    let p = &node.params;
    let wall = params.speed.max(1.0);
    let mut options = SessionOptions::new(
        params.steps.steps_per_unit,
        params.joint_accelerations,
        params.pin_open_delay_s,
    );
    options.horizon_s = params.horizon_s;
    options.lead_s = p.f64("lead_s") * wall;
    options.state_period_s = p.f64("state_period_s");
    options.clock_query_period_s = p.f64("clock_query_period_s");
    options.clock_query_settled_period_s = p.f64("clock_query_settled_period_s");
    options.host_timeout_s = p.f64("host_timeout_s") * wall;
    options.silence_s = p.f64("silence_s") * wall;
    options.answer_timeout_s = p.f64("answer_timeout_s") * wall;
    options.retransmit_timeout_s = p.f64("retransmit_timeout_s") * wall;
    options.pack_s = p.f64("pack_s");
    options.screw_hold = params.screw_hold;
    options
}

/// The device is not there (yet), as opposed to there and unusable.
fn absent(e: &anyhow::Error) -> bool {
    e.chain()
        .filter_map(|c| c.downcast_ref::<std::io::Error>())
        .any(|io| {
            matches!(
                io.kind(),
                ErrorKind::NotFound | ErrorKind::ConnectionRefused
            )
        })
}

/// Open the device, looking for it for up to `timeout`: it may appear a moment after we
/// start (a USB MCU enumerating, an emulator binding its socket).
fn open_waiting(
    spec: &str,
    baud: u32,
    timeout: std::time::Duration,
) -> anyhow::Result<(Device, String)> {
    let give_up = std::time::Instant::now() + timeout;
    loop {
        match Device::open(spec, baud) {
            Ok(opened) => return Ok(opened),
            Err(e) if std::time::Instant::now() < give_up && absent(&e) => {
                std::thread::sleep(std::time::Duration::from_millis(100));
            }
            Err(e) => return Err(e),
        }
    }
}

/// A nonce for this host session (the MCU learns from it that the host restarted).
fn session_nonce() -> u32 {
    let t = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default();
    (t.subsec_nanos() ^ (t.as_secs() as u32).rotate_left(16) ^ std::process::id()) | 1
}

/// Where the MCU on `spec` stands, in steps of bed, arm and z: a short session of its own
/// (identify, configure, reset, the clocks, a state reported after the reset) before a print
/// is planned, so that the plan starts where the machine is. The MCU keeps its position;
/// the bridge's session that follows resets it again (and clears the HOST_SILENT this one
/// leaves if it takes longer than the host timeout to come).
pub fn probe_position(
    spec: &str,
    baud: u32,
    options: SessionOptions,
    timeout: std::time::Duration,
) -> anyhow::Result<[i64; 3]> {
    use cell_machine::Machine as _;
    let give_up = std::time::Instant::now() + timeout;
    let (device, name) = open_waiting(spec, baud, timeout)?;
    let session = McuSession::new(options, session_nonce());
    let link = SerialLink::new(device, name.clone()).stamping_arrivals()?;
    // No plan goes to it (so its start is never checked): a place or two, any horizon.
    let mut machine = McuMachine::new(session, link, 2, 1.0);
    let started = std::time::Instant::now();
    machine.clock_started(started, 1.0);
    loop {
        let now_ns = started.elapsed().as_nanos() as i64;
        machine
            .on_tick(now_ns)
            .map_err(|e| anyhow::anyhow!("asking the MCU on {name} where it stands: {e}"))?;
        // (An MCU that does not answer: the session says what it waited for.)
        if let Some(e) = machine.session().error() {
            anyhow::bail!("asking the MCU on {name} where it stands: {e}");
        }
        // Room for a plan: identified, configured, reset acted on, clocks known, a state.
        if machine.free_slots().0 > 0 {
            if let Some(state) = machine.session().state() {
                return Ok(state.position_steps.map(i64::from));
            }
        }
        if std::time::Instant::now() > give_up {
            anyhow::bail!(
                "the MCU on {name} did not say where it stands within {:.1} s",
                timeout.as_secs_f64()
            );
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
}

/// Run the bridge on `node` until an error: the MCU on `device` is the machine.
pub async fn run(
    node: &mut CellNode,
    commands: mpsc::UnboundedReceiver<Request>,
    status: watch::Sender<Status>,
) -> anyhow::Result<()> {
    let params = MachineParams::from_params(&node.params)?;
    let spec = node.params.string("device").to_string();
    if spec.is_empty() {
        anyhow::bail!(
            "parameter device is empty: say where the MCU is (-p device:=/dev/ttyACM0, a \
             pseudo-terminal's path, or unix:/path)"
        );
    }
    let baud = node.params.i64("baud") as u32;
    let timeout = std::time::Duration::from_secs_f64(node.params.f64("open_timeout_s"));
    // Waiting for the device blocks: off the runtime's threads.
    let (device, name) =
        tokio::task::spawn_blocking(move || open_waiting(&spec, baud, timeout)).await??;
    cell_runtime::cell_log!(node, LogLevel::Info, "MCU on {name}");
    let session = McuSession::new(session_options(node, &params), session_nonce());
    let link = SerialLink::new(device, name).stamping_arrivals()?;
    let machine = McuMachine::new(session, link, params.queue_capacity, params.horizon_s)
        .with_start_steps(params.initial_steps());
    let Some(port) = screw_port(node, &params)? else {
        let mut machine = machine;
        return cell_machine::node::run(node, &mut machine, &params, commands, status).await;
    };
    let mut machine = WithScrewLine::new(machine, port.1, port.0, params.queue_capacity);
    machine
        .start_stopped()
        .context("parameter screw_port: the first line (rpm 0, pin closed)")?;
    cell_machine::node::run(node, &mut machine, &params, commands, status).await
}

/// The screw's serial line and its commands, if parameter `screw_port` names one.
fn screw_port(
    node: &CellNode,
    params: &MachineParams,
) -> anyhow::Result<Option<(SerialLink, ScrewLine)>> {
    let p = &node.params;
    let spec = p.string("screw_port");
    if spec.is_empty() {
        return Ok(None);
    }
    let template = CommandTemplate::parse(p.string("screw_command_template"))
        .context("parameter screw_command_template")?;
    let framing: Framing = p
        .string("screw_port_framing")
        .parse()
        .context("parameter screw_port_framing")?;
    let baud = p.i64("screw_port_baud") as u32;
    let rate_hz = p.f64("screw_max_rate_hz");
    // Half the line at most: a line written while the last is still going out waits in the
    // port, and so would a stop behind it.
    let needed = template.bits_per_s(rate_hz, framing.bits_per_character());
    if needed > 0.5 * baud as f64 {
        anyhow::bail!(
            "parameters screw_max_rate_hz ({rate_hz}) and screw_port_baud ({baud}): lines at \
             1,000 rpm, {rate_hz} a second, need {needed:.0} bit/s, more than half of the \
             line's {baud} baud ({}): lines would queue and a stop would reach the amplifier \
             late; lower the rate, shorten the template or raise the baud rate",
            p.string("screw_port_framing")
        );
    }
    let (device, name) = Device::open_framed(spec, baud, framing)
        .context("parameter screw_port (the screw amplifier's line)")?;
    cell_runtime::cell_log!(
        node,
        LogLevel::Info,
        "screw on {name}: at most {rate_hz} commands/s, as {:?}",
        p.string("screw_command_template")
    );
    let line = ScrewLine::new(template, rate_hz, params.screw_hold);
    Ok(Some((SerialLink::new(device, name), line)))
}

/// Run the node from its own command line until SIGINT/SIGTERM.
pub async fn main_with_args(argv: Vec<String>) -> anyhow::Result<()> {
    cell_machine::node::main_with_args(NODE_NAME, &param_specs(), argv, |node, rx, tx| {
        Box::pin(run(node, rx, tx))
    })
    .await
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    /// Bytes go on the machine's clock by when they came, whatever `now_ns` the look that
    /// takes them is given: the node's first looks of a pass are at grid instants behind the
    /// wall clock (a stamp counted back from them came out early by the lag).
    #[test]
    fn arrivals_are_placed_on_the_machines_clock_not_counted_back_from_the_look() {
        let (ours, mut mcu) = UnixStream::pair().unwrap();
        ours.set_nonblocking(true).unwrap();
        let mut link = SerialLink::new(Device::Socket(ours), "pair".into())
            .stamping_arrivals()
            .unwrap();
        let origin = Instant::now();
        let speed = 10.0;
        link.clock_started(origin, speed);
        std::thread::sleep(Duration::from_millis(20));
        mcu.write_all(b"reply\x00").unwrap();
        let sent_ns = (origin.elapsed().as_nanos() as f64 * speed) as i64;
        std::thread::sleep(Duration::from_millis(30));
        // A look at a grid instant 100 ms of machine time behind the wall clock.
        let stale_now_ns = (origin.elapsed().as_nanos() as f64 * speed) as i64 - 100_000_000;
        let (mut into, mut arrivals) = (Vec::new(), Vec::new());
        link.read_arrivals(stale_now_ns, &mut into, &mut arrivals)
            .unwrap();
        assert_eq!(into, b"reply\x00");
        let [(end, at_ns)] = arrivals[..] else {
            panic!("{arrivals:?}")
        };
        assert_eq!(end, 6);
        // Within a few ms of wall time (10× in machine time) of the write.
        let late_ns = at_ns - sent_ns;
        assert!(
            (-1_000_000..50_000_000).contains(&late_ns),
            "stamped {late_ns} ns after the write"
        );
    }
}
