//! The host's side of the cell's MCU protocol, without I/O.
//!
//! * [`host`] — the host's protocol endpoint: typed messages over the link;
//! * [`clock`] — what the MCU clock reads at a host instant, estimated from clock queries;
//! * [`schedule`] — the plan's step segments and screw commands on the MCU's plan clock;
//! * [`session`] — one MCU's session: start, identify, clocks, the plan fed within the horizon;
//! * [`screw_line`] — the screw on an ASCII serial line (a servo amplifier), rate-limited;
//! * [`machine`] — an MCU as the cell's machine: what the node loop drives;
//! * [`screw_port`] — any machine with its screw on such a line instead;
//! * [`node`] (feature `node`) — the `mcu_bridge` node: the serial line and the ROS face.

pub mod clock;
pub mod host;
#[cfg(feature = "node")]
pub mod line_reader;
pub mod machine;
#[cfg(feature = "node")]
pub mod node;
pub mod schedule;
pub mod screw_line;
pub mod screw_port;
pub mod session;

pub use clock::{ClockFit, ClockSync};
pub use host::{FromMcu, HostEndpoint};
pub use machine::{McuLink, McuMachine, McuMachineError};
pub use schedule::{Schedule, ScheduleError};
pub use screw_line::{CommandTemplate, LineClock, ScrewLine, ScrewLineError, TemplateError};
pub use screw_port::{LinePort, WithScrewLine, WithScrewLineError};
pub use session::{McuSession, SessionError, SessionOptions};
