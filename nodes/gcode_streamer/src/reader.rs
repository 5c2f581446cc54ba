//! Incremental reading: one line at a time from any `BufRead`, so memory does not grow with the
//! file's length (only with its longest line, which is capped).
//!
//! Lines that lie whole in the reader's buffer are interpreted in place, without a copy; only a
//! line split across two buffer fills is assembled in a side buffer.

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
    /// A line split across buffer fills, assembled here.
    partial: Vec<u8>,
    /// The current line's output, served warnings first, then moves.
    output: LineOutput,
    next_warning: usize,
    next_move: usize,
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
            partial: Vec::new(),
            output: LineOutput::default(),
            next_warning: 0,
            next_move: 0,
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

    fn io_error(&self, e: std::io::Error) -> GcodeError {
        GcodeError {
            file: self.file.clone(),
            line: self.line_number + 1,
            column: 0,
            kind: ErrorKind::Io(e.to_string()),
        }
    }

    fn too_long(&mut self) -> GcodeError {
        self.finished = true;
        GcodeError {
            file: self.file.clone(),
            line: self.line_number,
            column: MAX_LINE_BYTES as u32,
            kind: ErrorKind::LineTooLong {
                limit: MAX_LINE_BYTES,
            },
        }
    }

    /// Interpret lines until the current line produced output or input ends.
    fn fill(&mut self) -> Result<(), GcodeError> {
        while !self.has_pending() && !self.finished {
            self.output.moves.clear();
            self.output.warnings.clear();
            self.next_warning = 0;
            self.next_move = 0;
            let buf = match self.input.fill_buf() {
                Ok(buf) => buf,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(self.io_error(e)),
            };
            if buf.is_empty() {
                self.finished = true;
                if self.partial.is_empty() {
                    break;
                }
                // Last line without a terminator.
                self.line_number += 1;
                let line = std::mem::take(&mut self.partial);
                self.interpreter
                    .feed_line(self.line_number, &line, &mut self.output)?;
                break;
            }
            let (consumed, result) = match memchr::memchr(b'\n', buf) {
                Some(end) if self.partial.is_empty() => {
                    self.line_number += 1;
                    let line = &buf[..end];
                    if line.len() > MAX_LINE_BYTES {
                        (end + 1, Err(()))
                    } else {
                        let r =
                            self.interpreter
                                .feed_line(self.line_number, line, &mut self.output);
                        (end + 1, Ok(r))
                    }
                }
                Some(end) => {
                    self.line_number += 1;
                    self.partial.extend_from_slice(&buf[..end]);
                    if self.partial.len() > MAX_LINE_BYTES {
                        (end + 1, Err(()))
                    } else {
                        let r = self.interpreter.feed_line(
                            self.line_number,
                            &self.partial,
                            &mut self.output,
                        );
                        self.partial.clear();
                        (end + 1, Ok(r))
                    }
                }
                None => {
                    self.partial.extend_from_slice(buf);
                    let n = buf.len();
                    if self.partial.len() > MAX_LINE_BYTES {
                        // The line has no end yet, but it is the next one: name it.
                        self.line_number += 1;
                        (n, Err(()))
                    } else {
                        (n, Ok(Ok(())))
                    }
                }
            };
            self.input.consume(consumed);
            self.bytes_read += consumed as u64;
            match result {
                Ok(Ok(())) => {}
                Ok(Err(e)) => {
                    self.output.moves.clear();
                    self.output.warnings.clear();
                    return Err(e);
                }
                Err(()) => {
                    return Err(self.too_long());
                }
            }
        }
        Ok(())
    }

    fn has_pending(&self) -> bool {
        self.next_warning < self.output.warnings.len() || self.next_move < self.output.moves.len()
    }
}

impl<R: BufRead> Iterator for GcodeReader<R> {
    type Item = Result<Event, GcodeError>;

    fn next(&mut self) -> Option<Self::Item> {
        if let Err(e) = self.fill() {
            return Some(Err(e));
        }
        if let Some(w) = self.output.warnings.get_mut(self.next_warning) {
            self.next_warning += 1;
            return Some(Ok(Event::Warning(std::mem::replace(
                w,
                Warning {
                    line: 0,
                    column: 0,
                    message: String::new(),
                },
            ))));
        }
        if let Some(m) = self.output.moves.get_mut(self.next_move) {
            self.next_move += 1;
            return Some(Ok(Event::Move(std::mem::take(m))));
        }
        None
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A reader whose buffer holds only a few bytes, so lines straddle buffer fills.
    #[test]
    fn lines_split_across_buffer_fills_parse_the_same() {
        let src = b"G1 X1.5 Y2\nG1 X3 ; comment\n\nG92 E0\nG1 X4 E1";
        let whole = parse_all(src, "w", InterpreterOptions::default()).unwrap();
        for capacity in 1..8 {
            let reader = std::io::BufReader::with_capacity(capacity, &src[..]);
            let mut moves = Vec::new();
            for e in GcodeReader::new(reader, "w", InterpreterOptions::default()) {
                if let Event::Move(m) = e.unwrap() {
                    moves.push(m);
                }
            }
            assert_eq!(moves, whole.0, "capacity {capacity}");
        }
        let mut r = GcodeReader::new(&src[..], "w", InterpreterOptions::default());
        assert_eq!(r.by_ref().count(), 4);
        assert_eq!(r.lines_read(), 5);
        assert_eq!(r.bytes_read(), src.len() as u64);
    }

    #[test]
    fn too_long_lines_are_errors_naming_their_line_whether_buffered_or_not() {
        let long = vec![b' '; MAX_LINE_BYTES + 10];
        for (prefix, line) in [
            (&b""[..], 1),
            (&b"G1 X1\n"[..], 2),
            (&b"G1 X1\n\nM107\n"[..], 4),
        ] {
            for newline in [false, true] {
                let mut src = prefix.to_vec();
                src.extend_from_slice(&long);
                if newline {
                    src.push(b'\n');
                }
                // Smaller than the line (cut while no newline is in sight), exactly the limit,
                // and larger than the whole input (the line arrives in one piece).
                for capacity in [1024, MAX_LINE_BYTES, 1 << 20] {
                    let reader = std::io::BufReader::with_capacity(capacity, &src[..]);
                    let err = GcodeReader::new(reader, "l", InterpreterOptions::default())
                        .find_map(|e| e.err())
                        .unwrap();
                    assert_eq!(
                        err.kind,
                        ErrorKind::LineTooLong {
                            limit: MAX_LINE_BYTES
                        }
                    );
                    assert_eq!(err.line, line, "capacity {capacity}, newline {newline}");
                }
            }
        }
    }
}
