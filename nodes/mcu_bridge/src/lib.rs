//! The host's side of the cell's MCU protocol, without I/O.
//!
//! * [`host`] — the host's protocol endpoint: typed messages over the link;
//! * [`clock`] — what the MCU clock reads at a host instant, estimated from clock queries.

pub mod clock;
pub mod host;

pub use clock::{ClockFit, ClockSync};
pub use host::{FromMcu, HostEndpoint};
