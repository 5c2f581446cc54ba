//! Incremental reading: one line at a time from any `BufRead`, so memory does not grow with the
//! file's length (only with its longest line, which is capped).

use std::collections::VecDeque;
use std::io::BufRead;

use polar_cell_msgs::GcodeMove;

use crate::error::{ErrorKind, GcodeError, Warning};
use crate::interp::{Interpreter, InterpreterOptions, LineOutput};

/// Longest line accepted; a longer one (a binary file, say) is an error, not an allocation.
pub const MAX_LINE_BYTES: usize = 64 * 1024;

/// What the reader yields.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    Move(GcodeMove),
    Warning(Warning),
}

/// Streams [`Event`]s out of G-code bytes.
pub struct GcodeReader<R> {
    input: R,
    interpreter: Interpreter,
    file: String,
    line_buf: Vec<u8>,
    pending: VecDeque<Event>,
    output: LineOutput,
    line_number: u32,
    bytes_read: u64,
    finished: bool,
}

impl<R: BufRead> GcodeReader<R> {
    pub fn new(input: R, file: impl Into<String>, options: InterpreterOptions) -> Self {
        let file = file.into();
        GcodeReader {
            input,
            interpreter: Interpreter::new(file.clone(), options),
            file,
            line_buf: Vec::with_capacity(256),
            pending: VecDeque::new(),
            output: LineOutput::default(),
            line_number: 0,
            bytes_read: 0,
            finished: false,
        }
    }

    /// Lines read so far.
    pub fn lines_read(&self) -> u32 {
        self.line_number
    }

    /// Bytes consumed so far.
    pub fn bytes_read(&self) -> u64 {
        self.bytes_read
    }

    /// Read lines until at least one event is pending or input ends.
    fn fill(&mut self) -> Result<(), GcodeError> {
        while self.pending.is_empty() && !self.finished {
            self.line_buf.clear();
            let n = std::io::Read::take(&mut self.input, MAX_LINE_BYTES as u64 + 1)
                .read_until(b'\n', &mut self.line_buf)
                .map_err(|e| GcodeError {
                    file: self.file.clone(),
                    line: self.line_number + 1,
                    column: 0,
                    kind: ErrorKind::Io(e.to_string()),
                })?;
            if n == 0 {
                self.finished = true;
                break;
            }
            self.bytes_read += n as u64;
            self.line_number += 1;
            let line = match self.line_buf.strip_suffix(b"\n") {
                Some(l) => l,
                None if n > MAX_LINE_BYTES => {
                    self.finished = true;
                    return Err(GcodeError {
                        file: self.file.clone(),
                        line: self.line_number,
                        column: MAX_LINE_BYTES as u32,
                        kind: ErrorKind::LineTooLong {
                            limit: MAX_LINE_BYTES,
                        },
                    });
                }
                None => &self.line_buf[..],
            };
            self.interpreter
                .feed_line(self.line_number, line, &mut self.output)
                .inspect_err(|_| {
                    self.output.moves.clear();
                    self.output.warnings.clear();
                })?;
            self.pending
                .extend(self.output.warnings.drain(..).map(Event::Warning));
            self.pending
                .extend(self.output.moves.drain(..).map(Event::Move));
        }
        Ok(())
    }
}

impl<R: BufRead> Iterator for GcodeReader<R> {
    type Item = Result<Event, GcodeError>;

    fn next(&mut self) -> Option<Self::Item> {
        if let Err(e) = self.fill() {
            return Some(Err(e));
        }
        self.pending.pop_front().map(Ok)
    }
}

/// Parse a whole in-memory file; convenient for tests and small tools.
pub fn parse_all(
    bytes: &[u8],
    file: &str,
    options: InterpreterOptions,
) -> Result<(Vec<GcodeMove>, Vec<Warning>), GcodeError> {
    let mut moves = Vec::new();
    let mut warnings = Vec::new();
    for event in GcodeReader::new(bytes, file, options) {
        match event? {
            Event::Move(m) => moves.push(m),
            Event::Warning(w) => warnings.push(w),
        }
    }
    Ok((moves, warnings))
}
