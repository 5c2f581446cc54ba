//! Errors and warnings, each naming the file, line and column and what was expected.

use std::fmt;

/// What went wrong on a line.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ErrorKind {
    #[error("expected {0}")]
    Expected(&'static str),
    #[error("expected a number after `{0}`")]
    ExpectedNumberAfter(char),
    #[error("unexpected character `{0}`")]
    UnexpectedChar(char),
    #[error("unexpected byte 0x{0:02X} (G-code is ASCII outside comments)")]
    UnexpectedByte(u8),
    #[error("`(` comment is not closed on this line")]
    UnterminatedComment,
    #[error("checksum mismatch: line says {given}, its bytes XOR to {computed}")]
    ChecksumMismatch { given: u8, computed: u8 },
    #[error("line number N{found} out of order: expected N{expected}")]
    LineNumberOutOfOrder { expected: i64, found: i64 },
    #[error("`{letter}` given twice in one command")]
    DuplicateWord { letter: char },
    #[error("{command}: {problem}")]
    InvalidCommand {
        command: String,
        problem: &'static str,
    },
    #[error("arc: {0}")]
    InvalidArc(String),
    #[error("value {value} of `{letter}` is not finite or out of range")]
    OutOfRange { letter: char, value: f64 },
    #[error("line is longer than {limit} bytes")]
    LineTooLong { limit: usize },
    #[error("read failed: {0}")]
    Io(String),
}

/// A G-code error at a place in a file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub struct GcodeError {
    /// File name as given by the caller (or `<stdin>`).
    pub file: String,
    /// 1-based line.
    pub line: u32,
    /// 1-based column (byte offset in the line + 1); 0 when not about a column.
    pub column: u32,
    pub kind: ErrorKind,
}

impl fmt::Display for GcodeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}:{}:{}: {}",
            self.file, self.line, self.column, self.kind
        )
    }
}

/// Something the streamer skipped or did not understand, but which does not stop a print.
#[derive(Debug, Clone, PartialEq)]
pub struct Warning {
    pub line: u32,
    pub column: u32,
    pub message: String,
}

impl fmt::Display for Warning {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "line {}:{}: {}", self.line, self.column, self.message)
    }
}
