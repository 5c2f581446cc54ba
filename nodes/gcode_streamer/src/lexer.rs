//! Splits one G-code line into words (`letter number`), without allocating.
//!
//! Handles what slicers and hosts write: `;` and `( )` comments, any case, words packed without
//! spaces (`G1X10Y10`), leading-dot and signed numbers (`E.04`, `X-.5`), `N` line numbers and a
//! trailing `*` checksum (the XOR of every byte before the `*`, as RepRap hosts compute it),
//! and the free-text argument of `M117`-like commands.

use crate::error::ErrorKind;

/// One `letter number` pair. `letter` is upper case; `column` is 1-based; `value` is NaN for a
/// bare letter (a flag word such as the axes of `G28 X Y`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Word {
    pub letter: u8,
    pub value: f64,
    pub column: u32,
}

/// Commands whose argument is free text up to the end of the line (or `;` comment): file
/// names, messages, and the slicers' object labels (`M486 AShape-Box`) and firmware checks
/// (`M115 U3.13.2`), which the streamer skips but whose text is no `letter number` words.
const TEXT_ARGUMENT_M_CODES: &[u32] = &[23, 28, 30, 32, 115, 117, 118, 486, 928];

/// Whether `M<code>` takes free text: the codes above, and PrusaSlicer's printer checks
/// `M862.1`…`M862.6` (`M862.3 P "MK3S"`).
fn takes_text_argument(code: f64) -> bool {
    (code.fract() == 0.0 && TEXT_ARGUMENT_M_CODES.contains(&(code as u32)))
        || (code.trunc() == 862.0 && code > 862.0)
}

/// The lexed content of one line.
#[derive(Debug, Default)]
pub struct LexedLine<'a> {
    /// Words in line order, `N` excluded.
    pub words: Vec<Word>,
    /// The `N` line number, when present.
    pub line_number: Option<i64>,
    /// Free-text argument of `M117` and friends.
    pub text: Option<&'a [u8]>,
}

/// A lexing failure at a 1-based column.
#[derive(Debug, PartialEq)]
pub struct LexError {
    pub column: u32,
    pub kind: ErrorKind,
}

/// Reusable lexer; keeps its word buffer between lines so lexing does not allocate.
#[derive(Debug, Default)]
pub struct Lexer {
    words: Vec<Word>,
}

impl Lexer {
    /// Lex one line (without its line terminator; a trailing `\r` is ignored).
    pub fn lex<'a>(&mut self, line: &'a [u8]) -> Result<LexedLine<'a>, LexError> {
        let mut words = std::mem::take(&mut self.words);
        words.clear();
        let result = lex_into(line, &mut words);
        match result {
            Ok((line_number, text)) => Ok(LexedLine {
                words,
                line_number,
                text,
            }),
            Err(e) => {
                self.words = words;
                Err(e)
            }
        }
    }

    /// Give the word buffer of a finished line back for reuse.
    pub fn recycle(&mut self, line: LexedLine<'_>) {
        self.words = line.words;
    }
}

fn lex_into<'a>(
    line: &'a [u8],
    words: &mut Vec<Word>,
) -> Result<(Option<i64>, Option<&'a [u8]>), LexError> {
    let line = line.strip_suffix(b"\r").unwrap_or(line);
    let mut i = 0usize;
    let mut line_number = None;
    let mut text = None;
    let col = |i: usize| (i + 1) as u32;
    while i < line.len() {
        let c = line[i];
        match c {
            b' ' | b'\t' => i += 1,
            b';' => break,
            b'(' => match line[i + 1..].iter().position(|&b| b == b')') {
                Some(close) => i += close + 2,
                None => {
                    return Err(LexError {
                        column: col(i),
                        kind: ErrorKind::UnterminatedComment,
                    })
                }
            },
            b'*' => {
                let checksum_col = col(i);
                if line_number.is_none() {
                    return Err(LexError {
                        column: checksum_col,
                        kind: ErrorKind::Expected("an N line number before a `*` checksum"),
                    });
                }
                let (value, end) = parse_unsigned(line, i + 1).ok_or(LexError {
                    column: col(i + 1),
                    kind: ErrorKind::Expected("a checksum (0-255) after `*`"),
                })?;
                if value > 255 {
                    return Err(LexError {
                        column: col(i + 1),
                        kind: ErrorKind::Expected("a checksum (0-255) after `*`"),
                    });
                }
                let computed = line[..i].iter().fold(0u8, |acc, &b| acc ^ b);
                if computed as u64 != value {
                    return Err(LexError {
                        column: checksum_col,
                        kind: ErrorKind::ChecksumMismatch {
                            given: value as u8,
                            computed,
                        },
                    });
                }
                ensure_only_trailing_comment(line, end)?;
                break;
            }
            _ if c.is_ascii_alphabetic() => {
                let letter = c.to_ascii_uppercase();
                let word_col = col(i);
                let mut j = i + 1;
                while j < line.len() && (line[j] == b' ' || line[j] == b'\t') {
                    j += 1;
                }
                let (value, end) = match parse_number(line, j) {
                    Some(parsed) => parsed,
                    // A bare letter (`G28 X Y`, `M84 X Y E`) is a flag word; its value is NaN
                    // and only the commands that take flags, or that are skipped, accept it
                    // (see the interpreter). A line's first word is never one: a line of text
                    // is no command.
                    None if matches!(
                        line.get(j),
                        None | Some(b' ' | b'\t' | b';' | b'(' | b'*')
                    ) || (!words.is_empty()
                        && line.get(j).is_some_and(|b| b.is_ascii_alphabetic())) =>
                    {
                        (f64::NAN, j)
                    }
                    None => {
                        return Err(LexError {
                            column: col(j),
                            kind: ErrorKind::ExpectedNumberAfter(letter as char),
                        })
                    }
                };
                i = end;
                if letter == b'N' && words.is_empty() && line_number.is_none() {
                    if value.fract() != 0.0 || value.is_nan() {
                        return Err(LexError {
                            column: word_col,
                            kind: ErrorKind::Expected("an integer line number after N"),
                        });
                    }
                    line_number = Some(value as i64);
                    continue;
                }
                words.push(Word {
                    letter,
                    value,
                    column: word_col,
                });
                if letter == b'M' && words.len() == 1 && takes_text_argument(value) {
                    let rest = &line[i..];
                    let stop = rest
                        .iter()
                        .position(|&b| b == b';' || b == b'*')
                        .unwrap_or(rest.len());
                    let t = trim(&rest[..stop]);
                    text = Some(t);
                    i += stop;
                }
            }
            _ => {
                return Err(LexError {
                    column: col(i),
                    kind: if c.is_ascii_graphic() {
                        ErrorKind::UnexpectedChar(c as char)
                    } else {
                        ErrorKind::UnexpectedByte(c)
                    },
                })
            }
        }
    }
    Ok((line_number, text))
}

fn ensure_only_trailing_comment(line: &[u8], mut i: usize) -> Result<(), LexError> {
    while i < line.len() {
        match line[i] {
            b' ' | b'\t' => i += 1,
            b';' => return Ok(()),
            _ => {
                return Err(LexError {
                    column: (i + 1) as u32,
                    kind: ErrorKind::Expected("end of line after the checksum"),
                })
            }
        }
    }
    Ok(())
}

fn trim(s: &[u8]) -> &[u8] {
    let start = s
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(s.len());
    let end = s
        .iter()
        .rposition(|b| !b.is_ascii_whitespace())
        .map_or(start, |p| p + 1);
    &s[start..end]
}

fn parse_unsigned(line: &[u8], start: usize) -> Option<(u64, usize)> {
    let mut i = start;
    let mut v: u64 = 0;
    while i < line.len() && line[i].is_ascii_digit() {
        v = v.checked_mul(10)?.checked_add((line[i] - b'0') as u64)?;
        i += 1;
    }
    (i > start).then_some((v, i))
}

/// Parse `[+-]digits[.digits]` or `[+-].digits` starting at `start`; returns the value and the
/// index after it. When the digits form an integer mantissa below 2^53 with at most 22
/// fraction digits, the result is the mantissa divided by an exact power of ten, which rounds
/// once and so equals `str::parse::<f64>` to the last bit; anything longer takes `str::parse`.
pub(crate) fn parse_number(line: &[u8], start: usize) -> Option<(f64, usize)> {
    let mut i = start;
    let negative = match line.get(i) {
        Some(b'-') => {
            i += 1;
            true
        }
        Some(b'+') => {
            i += 1;
            false
        }
        _ => false,
    };
    let (after_int, mut mantissa) = accumulate_digits(line, i, 0);
    let int_digits = after_int - i;
    i = after_int;
    let mut frac_digits = 0;
    if line.get(i) == Some(&b'.') {
        let (after_frac, m) = accumulate_digits(line, i + 1, mantissa);
        frac_digits = after_frac - (i + 1);
        mantissa = m;
        i = after_frac;
    }
    if int_digits + frac_digits == 0 {
        return None;
    }
    // 19 digits cannot overflow u64; below 2^53 the mantissa is exact in f64.
    if int_digits + frac_digits <= 19 && mantissa < (1u64 << 53) && frac_digits <= 22 {
        let value = mantissa as f64 / POW10[frac_digits];
        return Some((if negative { -value } else { value }, i));
    }
    let s = std::str::from_utf8(&line[start..i]).ok()?;
    let s = s.strip_suffix('.').unwrap_or(s);
    s.parse::<f64>().ok().map(|v| (v, i))
}

/// Append the decimal digits starting at `i` to `mantissa` (wrapping: callers check the digit
/// count); returns the index after the digits and the new mantissa.
fn accumulate_digits(line: &[u8], mut i: usize, mut mantissa: u64) -> (usize, u64) {
    while let Some(&b) = line.get(i) {
        let d = b.wrapping_sub(b'0');
        if d > 9 {
            break;
        }
        mantissa = mantissa.wrapping_mul(10).wrapping_add(d as u64);
        i += 1;
    }
    (i, mantissa)
}

const POW10: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];

#[cfg(test)]
mod tests {
    use super::*;

    fn lex(s: &str) -> Result<Vec<(char, f64)>, LexError> {
        let mut lexer = Lexer::default();
        lexer.lex(s.as_bytes()).map(|l| {
            l.words
                .iter()
                .map(|w| (w.letter as char, w.value))
                .collect()
        })
    }

    #[test]
    fn packed_lowercase_leading_dot_and_signs() {
        assert_eq!(
            lex("g1x10Y-.5 e.04 F+300").unwrap(),
            [
                ('G', 1.0),
                ('X', 10.0),
                ('Y', -0.5),
                ('E', 0.04),
                ('F', 300.0)
            ]
        );
    }

    #[test]
    fn comments_of_both_kinds() {
        assert_eq!(
            lex("G1 (move x) X1 ; Y2").unwrap(),
            [('G', 1.0), ('X', 1.0)]
        );
        assert_eq!(lex("(only a comment)").unwrap(), []);
        let err = lex("G1 (open X1").unwrap_err();
        assert_eq!(err.column, 4);
        assert_eq!(err.kind, ErrorKind::UnterminatedComment);
    }

    #[test]
    fn numbers_match_std_parse_exactly() {
        for s in [
            "0.1",
            "-2.922",
            "1.202",
            "123456.789012",
            "0.0000001",
            ".5",
            "5.",
            "007",
        ] {
            let (v, end) = parse_number(s.as_bytes(), 0).unwrap();
            assert_eq!(end, s.len());
            let expected: f64 = s.trim_end_matches('.').parse().unwrap();
            assert_eq!(v.to_bits(), expected.to_bits(), "{s}");
        }
        let long = "3.14159265358979323846264338";
        assert_eq!(
            parse_number(long.as_bytes(), 0).unwrap().0,
            long.parse::<f64>().unwrap()
        );
        assert_eq!(parse_number(b"-", 0), None);
        assert_eq!(parse_number(b".", 0), None);
    }

    #[test]
    fn checksums_are_verified() {
        // XOR of "N1 G1 X1" computed independently below.
        let body = "N1 G1 X1";
        let sum = body.bytes().fold(0u8, |a, b| a ^ b);
        let mut lexer = Lexer::default();
        let text = format!("{body}*{sum}");
        let ok = lexer.lex(text.as_bytes()).unwrap();
        assert_eq!(ok.line_number, Some(1));
        assert_eq!(ok.words.len(), 2);
        let bad = lex(&format!("{body}*{}", sum ^ 1)).unwrap_err();
        assert_eq!(
            bad.kind,
            ErrorKind::ChecksumMismatch {
                given: sum ^ 1,
                computed: sum
            }
        );
        assert_eq!(bad.column, 9);
        assert!(matches!(
            lex("G1 X1*5").unwrap_err().kind,
            ErrorKind::Expected(_)
        ));
    }

    #[test]
    fn text_argument_and_bad_bytes() {
        let mut lexer = Lexer::default();
        let l = lexer.lex(b"M117 Printing layer 3 ; comment").unwrap();
        assert_eq!(l.text, Some(&b"Printing layer 3"[..]));
        let err = lex("G1 X1 \u{e9}").unwrap_err();
        assert_eq!(err.column, 7);
        assert_eq!(err.kind, ErrorKind::UnexpectedByte(0xC3));
        let err = lex("G1 X=1").unwrap_err();
        assert_eq!(err.kind, ErrorKind::ExpectedNumberAfter('X'));
        assert_eq!(err.column, 5);
    }

    fn is_flag(word: (char, f64), letter: char) -> bool {
        word.0 == letter && word.1.is_nan()
    }

    /// Cura's Creality end code (`M84 X Y E`) and `G28 X Y`: bare letters before another word.
    #[test]
    fn flag_words_followed_by_other_words() {
        let words = lex("M84 X Y E ;Disable all steppers but Z").unwrap();
        assert_eq!(words.len(), 4);
        assert_eq!(words[0], ('M', 84.0));
        for (w, letter) in words[1..].iter().zip(['X', 'Y', 'E']) {
            assert!(is_flag(*w, letter), "{words:?}");
        }
        let words = lex("G28 XY Z0").unwrap();
        assert!(
            is_flag(words[1], 'X') && is_flag(words[2], 'Y'),
            "{words:?}"
        );
        assert_eq!(words[3], ('Z', 0.0));
        // A line's first word is never a flag: text is no command.
        let err = lex("Hello world").unwrap_err();
        assert_eq!(err.kind, ErrorKind::ExpectedNumberAfter('H'));
        assert_eq!(err.column, 2);
        // A letter before a character that starts no word is still an error.
        assert_eq!(
            lex("G1 X=1 Y").unwrap_err().kind,
            ErrorKind::ExpectedNumberAfter('X')
        );
    }

    /// PrusaSlicer's object labels and printer checks carry text, not words.
    #[test]
    fn object_labels_and_printer_checks_are_text() {
        let mut lexer = Lexer::default();
        for (line, text) in [
            ("M486 AShape-Box", "AShape-Box"),
            ("M486 S-1", "S-1"),
            ("M115 U3.13.2 ; tell the firmware version", "U3.13.2"),
            ("M862.3 P \"MK3S\"", "P \"MK3S\""),
            ("M862.1 P0.4", "P0.4"),
        ] {
            let l = lexer.lex(line.as_bytes()).unwrap();
            assert_eq!(l.words.len(), 1, "{line}");
            assert_eq!(l.text, Some(text.as_bytes()), "{line}");
            lexer.recycle(l);
        }
        // Not a text command: its words are lexed.
        assert_eq!(lex("M862 P1").unwrap(), [('M', 862.0), ('P', 1.0)]);
    }
}
