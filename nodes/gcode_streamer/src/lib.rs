//! G-code in, moves out: the pure core of the `gcode_streamer` node.
//!
//! * [`lexer`] splits a line into words (comments, checksums, packed words);
//! * [`interp`] is the modal machine that turns words into [`GcodeMove`]s in SI units;
//! * [`reader`] streams a file of any length line by line;
//!
//! No DDS, no files, no async here: bytes in, moves out. The node binary wires it to topics.

pub mod error;
pub mod interp;
pub mod lexer;
pub mod reader;

pub use error::{ErrorKind, GcodeError, Warning};
pub use interp::{Interpreter, InterpreterOptions, LineOutput};
pub use polar_cell_msgs::GcodeMove;
pub use reader::{parse_all, Event, GcodeReader};

#[cfg(feature = "node")]
pub mod node;
