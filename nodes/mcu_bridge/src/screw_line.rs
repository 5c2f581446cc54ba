//! The screw on an ASCII serial line: the real cell's servo amplifier.
//!
//! Seed 000 (§6.3) says the original cell commands its screw's servo amplifier with ASCII
//! strings over RS-232C, not with pulses — which is why fine rpm ramps were impractical there.
//! This module turns the screw driver's commands into such strings, sans I/O: a
//! [`CommandTemplate`] says what a line looks like (the seeds do not give the amplifier's
//! syntax, so it is the user's), and a [`ScrewLine`] says which line to send when.
//!
//! # At most `max_rate_hz` lines, and the material kept
//!
//! An amplifier takes a command a few times a second at most, and holds it until the next.
//! So a line holds one rpm over an interval of plan time, and that rpm is the exact average
//! of the commanded profile over the interval (held or linear between commands, as the screw
//! driver publishes them). Line `k+1` starts at the first command after line `k`'s start, but
//! not sooner than `1/max_rate_hz` after it: commands the screw driver already puts on a grid
//! of that period (its `command_period_s`, which averages exactly too) pass one for one;
//! faster ones are averaged here. Whatever a line could not deliver — its value rounded to the
//! template's resolution, a command that arrived after its line was computed — is owed to the
//! next line, so the material over a stretch of open pin is the plan's to the template's
//! resolution. A pin change inside a line's interval waits for the next line (counted: the
//! screw driver's pin delay is honoured only as closely as the rate allows).
//!
//! # Holds and stops
//!
//! The MCU scales the screw with the feed scale σ of a hold, keeps the pin open while it
//! slows and closes it once held at rest; lines here follow it (at the rate limit), so the
//! screw stops with the steppers. A line never says rpm > 0 with the pin closed. "rpm 0, pin
//! closed" goes out at once whatever the rate limit: at the end of a hold, and for an
//! emergency stop, a fault or a dropped plan. A line whose write failed leaves the
//! amplifier's state unknown ([`ScrewLine::forget_sent`]), so the next stop is sent again.

use std::collections::VecDeque;

use polar_cell_msgs::Hold;

/// Why a template cannot be used.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TemplateError {
    #[error("command template: `{{` at byte {at} is not closed by `}}`")]
    Unclosed { at: usize },
    #[error(
        "command template: `{{{name}}}` at byte {at} is not one of {{rpm}}, {{rpm:.N}} (N \
         decimals, 0 to 6), {{millirpm}}, {{pin}} or {{pin:OPEN/CLOSED}}"
    )]
    Unknown { name: String, at: usize },
    #[error(
        "command template: `\\{escape}` at byte {at} is not one of \\r, \\n, \\t, \\\\ or \\xHH"
    )]
    BadEscape { escape: String, at: usize },
    #[error("command template: a lone `}}` at byte {at} (write `}}}}` for a brace)")]
    LoneBrace { at: usize },
    #[error(
        "command template: `{{{name}}}` at byte {at} needs two different, non-empty words for \
         the open and the closed pin (a stop line must say the pin closed)"
    )]
    PinWords { name: String, at: usize },
    #[error("command template: {character:?} at byte {at} is not ASCII (an ASCII line)")]
    NotAscii { character: char, at: usize },
    #[error("command template {template:?} has no {missing}: the amplifier must be told it")]
    Missing {
        template: String,
        missing: &'static str,
    },
}

#[derive(Clone, Debug, PartialEq)]
enum Piece {
    Text(String),
    Rpm { decimals: usize },
    MilliRpm,
    Pin { open: String, closed: String },
}

/// What one command line looks like: text with `{rpm}` (3 decimals), `{rpm:.N}` (N
/// decimals), `{millirpm}` (a whole number), `{pin}` (1 open, 0 closed) or `{pin:OPEN/CLOSED}`
/// (the two words to use); `{{` and `}}` for braces; `\r`, `\n`, `\t`, `\\`, `\xHH` for
/// control bytes (a parameter string cannot hold them as they are).
#[derive(Clone, Debug, PartialEq)]
pub struct CommandTemplate {
    pieces: Vec<Piece>,
    /// The smallest rpm step the line can express (its first rpm field's).
    quantum_rpm: f64,
}

/// The documented default: one line per command, `RPM 12.3 PIN 1` and a carriage return and
/// line feed.
pub const DEFAULT_TEMPLATE: &str = "RPM {rpm:.1} PIN {pin}\\r\\n";

impl CommandTemplate {
    pub fn parse(template: &str) -> Result<CommandTemplate, TemplateError> {
        let mut pieces = Vec::new();
        let mut text = String::new();
        let bytes = template.as_bytes();
        let mut i = 0;
        while i < template.len() {
            let c = template[i..].chars().next().expect("inside the string");
            match c {
                '{' if bytes.get(i + 1) == Some(&b'{') => {
                    text.push('{');
                    i += 2;
                }
                '}' if bytes.get(i + 1) == Some(&b'}') => {
                    text.push('}');
                    i += 2;
                }
                '}' => return Err(TemplateError::LoneBrace { at: i }),
                '{' => {
                    let close = template[i..]
                        .find('}')
                        .ok_or(TemplateError::Unclosed { at: i })?;
                    let name = &template[i + 1..i + close];
                    if !text.is_empty() {
                        pieces.push(Piece::Text(std::mem::take(&mut text)));
                    }
                    pieces.push(placeholder(name, i)?);
                    i += close + 1;
                }
                '\\' => {
                    let (byte, len) =
                        escape(&template[i..]).ok_or_else(|| TemplateError::BadEscape {
                            escape: template[i + 1..].chars().take(3).collect(),
                            at: i,
                        })?;
                    text.push(byte as char);
                    i += len;
                }
                c if !c.is_ascii() => {
                    return Err(TemplateError::NotAscii {
                        character: c,
                        at: i,
                    })
                }
                c => {
                    text.push(c);
                    i += c.len_utf8();
                }
            }
        }
        if !text.is_empty() {
            pieces.push(Piece::Text(text));
        }
        let quantum_rpm = pieces
            .iter()
            .find_map(|p| match p {
                Piece::Rpm { decimals } => Some(10f64.powi(-(*decimals as i32))),
                Piece::MilliRpm => Some(1e-3),
                _ => None,
            })
            .ok_or_else(|| TemplateError::Missing {
                template: template.to_string(),
                missing: "{rpm}",
            })?;
        if !pieces.iter().any(|p| matches!(p, Piece::Pin { .. })) {
            return Err(TemplateError::Missing {
                template: template.to_string(),
                missing: "{pin}",
            });
        }
        Ok(CommandTemplate {
            pieces,
            quantum_rpm,
        })
    }

    /// The smallest rpm step a line can express.
    pub fn quantum_rpm(&self) -> f64 {
        self.quantum_rpm
    }

    /// Bits a second the line needs at `rate_hz` lines of `bits_per_character` (start, data,
    /// parity and stop bits) when it says 1,000 rpm: what the baud rate must carry with room
    /// to spare, or lines queue in the port and a stop reaches the amplifier late.
    pub fn bits_per_s(&self, rate_hz: f64, bits_per_character: u32) -> f64 {
        let longest = self
            .render(1000.0, true)
            .len()
            .max(self.render(1000.0, false).len());
        rate_hz * (longest as u32 * bits_per_character) as f64
    }

    /// `rpm` as the line will say it.
    pub fn quantize(&self, rpm: f64) -> f64 {
        (rpm.max(0.0) / self.quantum_rpm).round() * self.quantum_rpm
    }

    /// The line for `rpm` and the pin.
    pub fn render(&self, rpm: f64, pin_open: bool) -> String {
        let rpm = self.quantize(rpm) + 0.0; // no "-0.0"
        let mut out = String::new();
        for piece in &self.pieces {
            match piece {
                Piece::Text(t) => out.push_str(t),
                Piece::Rpm { decimals } => out.push_str(&format!("{rpm:.decimals$}")),
                Piece::MilliRpm => out.push_str(&format!("{}", (rpm * 1e3).round() as i64)),
                Piece::Pin { open, closed } => out.push_str(if pin_open { open } else { closed }),
            }
        }
        out
    }
}

fn placeholder(name: &str, at: usize) -> Result<Piece, TemplateError> {
    let unknown = || TemplateError::Unknown {
        name: name.to_string(),
        at,
    };
    Ok(match name {
        "rpm" => Piece::Rpm { decimals: 3 },
        "millirpm" => Piece::MilliRpm,
        "pin" => Piece::Pin {
            open: "1".into(),
            closed: "0".into(),
        },
        _ => {
            if let Some(decimals) = name.strip_prefix("rpm:.") {
                match decimals.parse::<usize>() {
                    Ok(d) if d <= 6 => Piece::Rpm { decimals: d },
                    _ => return Err(unknown()),
                }
            } else if let Some(words) = name.strip_prefix("pin:") {
                let (open, closed) = words.split_once('/').ok_or_else(unknown)?;
                if open.is_empty() || closed.is_empty() || open == closed {
                    return Err(TemplateError::PinWords {
                        name: name.to_string(),
                        at,
                    });
                }
                if let Some(character) = words.chars().find(|c| !c.is_ascii()) {
                    return Err(TemplateError::NotAscii { character, at });
                }
                Piece::Pin {
                    open: open.to_string(),
                    closed: closed.to_string(),
                }
            } else {
                return Err(unknown());
            }
        }
    })
}

/// The byte a backslash escape at the start of `s` stands for, and its length.
fn escape(s: &str) -> Option<(u8, usize)> {
    let b = s.as_bytes();
    Some(match b.get(1)? {
        b'r' => (b'\r', 2),
        b'n' => (b'\n', 2),
        b't' => (b'\t', 2),
        b'\\' => (b'\\', 2),
        b'x' => {
            let hex = s.get(2..4)?;
            let byte = u8::from_str_radix(hex, 16).ok()?;
            // Bytes above 0x7f would not be one character of an ASCII line.
            if byte > 0x7f {
                return None;
            }
            (byte, 4)
        }
        _ => return None,
    })
}

/// Why a screw command cannot go on the line.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ScrewLineError {
    #[error("screw command of line {source_line}: rpm {rpm} is not a finite number ≥ 0")]
    BadRpm { source_line: u32, rpm: f64 },
    #[error(
        "screw command of line {source_line} at plan time {plan_s} s comes before the \
         previous one at {previous_s} s"
    )]
    OutOfOrder {
        source_line: u32,
        plan_s: f64,
        previous_s: f64,
    },
}

/// One screw command on the plan clock.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Point {
    plan_s: f64,
    rpm: f64,
    pin_open: bool,
}

/// A scheduled line: from `start_s` of plan time, hold `rpm` with the pin so.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Scheduled {
    id: u64,
    start_s: f64,
    rpm: f64,
    pin_open: bool,
}

/// The last line sent.
#[derive(Clone, Debug, PartialEq)]
struct Sent {
    machine_s: f64,
    /// When it was due (machine time): the rate limit spaces what is due, not when a poll
    /// happened to notice it.
    due_s: f64,
    text: String,
    rpm: f64,
    pin_open: bool,
    line_id: u64,
}

/// Where the machine is when the line is polled.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LineClock {
    /// Machine time now (s): the rate limit is counted in it.
    pub machine_s: f64,
    /// Plan time executed by now (s); infinite once the plan has ended (its clock stops
    /// there, and the lines due after its end are due now).
    pub plan_s: f64,
    /// The feed scale σ the screw is scaled with (1 running, 0 held or idle).
    pub feed: f64,
    /// The pin may be open (not held closed by a hold or a stop).
    pub pin_allowed: bool,
}

/// What the line has done, for `/diagnostics` and tests.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LineCounters {
    pub lines_sent: u64,
    /// Lines sent after their start because the rate limit (or the caller's poll) made them
    /// wait, and the worst of that lateness (s of plan time).
    pub worst_late_s: f64,
    /// Pin changes that fell inside another line's interval and waited for the next line,
    /// and the longest wait (s of plan time).
    pub pin_changes_delayed: u64,
    pub worst_pin_delay_s: f64,
    /// Scheduled lines overtaken by the next before they could be sent (a stalled caller).
    pub lines_overtaken: u64,
    /// The shortest time between two lines sent (s of machine time): a period, less the
    /// poll's lateness of the earlier one.
    pub shortest_spacing_s: f64,
}

impl Default for LineCounters {
    fn default() -> Self {
        LineCounters {
            lines_sent: 0,
            worst_late_s: 0.0,
            pin_changes_delayed: 0,
            worst_pin_delay_s: 0.0,
            lines_overtaken: 0,
            shortest_spacing_s: f64::INFINITY,
        }
    }
}

/// The screw's commands as lines at most `1/min_period_s` a second.
#[derive(Clone, Debug)]
pub struct ScrewLine {
    template: CommandTemplate,
    hold: Hold,
    min_period_s: f64,
    /// Commands from the one in force at the current line's start on.
    points: VecDeque<Point>,
    current: Option<Scheduled>,
    next_start_s: Option<f64>,
    /// Material (rpm·s) the lines sent so far fell short of the profile by.
    owed_rpm_s: f64,
    sent: Option<Sent>,
    next_id: u64,
    counters: LineCounters,
}

impl ScrewLine {
    /// Lines rendered by `template`, at most `max_rate_hz` of them a second of machine time,
    /// for commands that run between each other as `hold` says.
    pub fn new(template: CommandTemplate, max_rate_hz: f64, hold: Hold) -> ScrewLine {
        ScrewLine {
            template,
            hold,
            min_period_s: 1.0 / max_rate_hz,
            points: VecDeque::new(),
            current: None,
            next_start_s: None,
            owed_rpm_s: 0.0,
            sent: None,
            next_id: 0,
            counters: LineCounters::default(),
        }
    }

    pub fn counters(&self) -> LineCounters {
        self.counters
    }

    /// The shortest time between two lines (s): `1 / max_rate_hz`.
    pub fn min_period_s(&self) -> f64 {
        self.min_period_s
    }

    pub fn template(&self) -> &CommandTemplate {
        &self.template
    }

    /// Commands held here (waiting for their line, or the one in force).
    pub fn queued(&self) -> usize {
        self.points.len()
    }

    /// The rpm and pin the amplifier was last told (0 and closed before any line).
    pub fn sent(&self) -> (f64, bool) {
        self.sent
            .as_ref()
            .map_or((0.0, false), |s| (s.rpm, s.pin_open))
    }

    /// Nothing more to send for the commands given (the last one's line went out).
    pub fn is_idle(&self) -> bool {
        self.next_start_s.is_none()
            && self.owed_rpm_s == 0.0
            && self
                .current
                .is_none_or(|c| self.sent.as_ref().is_some_and(|s| s.line_id == c.id))
    }

    /// Queue a command at `plan_s` of plan time.
    pub fn push(
        &mut self,
        plan_s: f64,
        rpm: f64,
        pin_open: bool,
        source_line: u32,
    ) -> Result<(), ScrewLineError> {
        if !(rpm.is_finite() && rpm >= 0.0) {
            return Err(ScrewLineError::BadRpm { source_line, rpm });
        }
        let plan_s =
            crate::schedule::screw_time_after(plan_s, self.points.back().map(|p| p.plan_s))
                .map_err(|previous_s| ScrewLineError::OutOfOrder {
                    source_line,
                    plan_s,
                    previous_s,
                })?;
        self.points.push_back(Point {
            plan_s,
            rpm,
            pin_open,
        });
        if self.next_start_s.is_none() {
            self.next_start_s = Some(match self.current {
                Some(c) => plan_s.max(c.start_s + self.min_period_s),
                None => plan_s,
            });
        }
        Ok(())
    }

    /// The line to send now, if any, and how late its schedule has it (s of plan time).
    pub fn poll(&mut self, clock: LineClock) -> Option<(String, f64)> {
        self.advance(clock.plan_s);
        let line = self.current?;
        let pin_open = line.pin_open && clock.pin_allowed;
        // Never a turning screw behind a closed pin (it would build pressure in the barrel).
        let rpm = if pin_open {
            self.template
                .quantize(line.rpm * clock.feed.clamp(0.0, 1.0))
        } else {
            0.0
        };
        // A machine that holds the pin closed (held at rest, idle, stopped: the line then
        // says rpm 0, pin closed) has it said at once, as an emergency stop is; the plan's
        // own lines, a pin closing on travel among them, keep the rate.
        let stopping = !clock.pin_allowed;
        if let Some(sent) = &self.sent {
            if (sent.rpm, sent.pin_open) == (rpm, pin_open) {
                if sent.line_id != line.id {
                    // The amplifier already holds what this line says.
                    self.sent.as_mut().expect("just seen").line_id = line.id;
                }
                return None;
            }
            if !stopping && clock.machine_s < sent.due_s + self.min_period_s - 1e-9 {
                return None;
            }
        }
        let new_line = self.sent.as_ref().is_none_or(|s| s.line_id != line.id);
        // A scheduled line was due at its start; one the poll found late is not the next
        // one's excuse to be later still (the schedule spaces starts a period apart).
        let late_s = if new_line && clock.plan_s.is_finite() {
            (clock.plan_s - line.start_s).max(0.0)
        } else {
            0.0
        };
        self.counters.worst_late_s = self.counters.worst_late_s.max(late_s);
        if let Some(sent) = &self.sent {
            let spacing_s = clock.machine_s - sent.machine_s;
            self.counters.shortest_spacing_s = self.counters.shortest_spacing_s.min(spacing_s);
        }
        let text = self.template.render(rpm, pin_open);
        self.counters.lines_sent += 1;
        self.sent = Some(Sent {
            machine_s: clock.machine_s,
            // A line held back by the rate is due when the rate allowed it, not earlier; a
            // stop, which did not wait, when it went.
            due_s: match &self.sent {
                Some(s) if !stopping => (clock.machine_s - late_s).max(s.due_s + self.min_period_s),
                Some(_) => clock.machine_s,
                None => clock.machine_s - late_s,
            },
            text: text.clone(),
            rpm,
            pin_open,
            line_id: line.id,
        });
        Some((text, late_s))
    }

    /// The last line may not have reached the amplifier (its write failed, perhaps half
    /// way): what it holds is unknown, so the next stop is sent whatever was sent before.
    pub fn forget_sent(&mut self) {
        self.sent = None;
    }

    /// Stop the screw now: rpm 0, pin closed, whatever the rate limit (unless it is so
    /// already); the commands are dropped.
    pub fn stop_now(&mut self, machine_s: f64) -> Option<String> {
        self.points.clear();
        self.current = None;
        self.next_start_s = None;
        self.owed_rpm_s = 0.0;
        if self
            .sent
            .as_ref()
            .is_some_and(|s| (s.rpm, s.pin_open) == (0.0, false))
        {
            return None;
        }
        let text = self.template.render(0.0, false);
        self.counters.lines_sent += 1;
        self.sent = Some(Sent {
            machine_s,
            due_s: machine_s,
            text: text.clone(),
            rpm: 0.0,
            pin_open: false,
            line_id: u64::MAX,
        });
        Some(text)
    }

    /// Schedule every line that has started by `plan_s`.
    fn advance(&mut self, plan_s: f64) {
        while let Some(start_s) = self.next_start_s.filter(|&s| s <= plan_s) {
            if let Some(previous) = self.current {
                self.owed_rpm_s += self.integral(previous.start_s, start_s)
                    - previous.rpm * (start_s - previous.start_s);
                if self.sent.as_ref().is_none_or(|s| s.line_id != previous.id) {
                    self.counters.lines_overtaken += 1;
                }
            }
            self.schedule(start_s);
        }
    }

    /// The line starting at `start_s`.
    fn schedule(&mut self, start_s: f64) {
        // Keep the command in force at the start (and what follows).
        while self.points.len() > 1 && self.points[1].plan_s <= start_s {
            self.points.pop_front();
        }
        let in_force = self.points.front().filter(|p| p.plan_s <= start_s);
        let pin_open = in_force.is_some_and(|p| p.pin_open);
        if !pin_open {
            // What was owed cannot flow through a closed pin; it is not carried to the next
            // opening, where it would land in the wrong place.
            self.owed_rpm_s = 0.0;
        }
        let next_command_s = self.points.iter().map(|p| p.plan_s).find(|&t| t > start_s);
        let (raw_rpm, next_start_s) = match next_command_s {
            Some(t) => {
                // A command a rounding away from a period after the start is on the grid.
                let earliest_s = start_s + self.min_period_s;
                let on_grid = |u: f64| u >= earliest_s - 1e-9;
                let end_s = if on_grid(t) {
                    t
                } else {
                    self.points
                        .iter()
                        .map(|p| p.plan_s)
                        .find(|&u| on_grid(u))
                        .filter(|&u| u <= earliest_s + 1e-9)
                        .unwrap_or(earliest_s)
                };
                let mut pin = pin_open;
                for p in self
                    .points
                    .iter()
                    .filter(|p| p.plan_s > start_s && p.plan_s < end_s)
                {
                    if p.pin_open != pin {
                        pin = p.pin_open;
                        self.counters.pin_changes_delayed += 1;
                        self.counters.worst_pin_delay_s =
                            self.counters.worst_pin_delay_s.max(end_s - p.plan_s);
                    }
                }
                let length_s = end_s - start_s;
                (
                    (self.integral(start_s, end_s) + self.owed_rpm_s) / length_s,
                    Some(end_s),
                )
            }
            // Constant from here on, as far as is known: held until a command comes; a debt
            // is paid over one period.
            None => {
                let value = self.value_at(start_s);
                let paying = value + self.owed_rpm_s / self.min_period_s;
                if self.template.quantize(paying) == self.template.quantize(value) {
                    // Less than the line can say: forgiven, or it would circle for ever.
                    self.owed_rpm_s = 0.0;
                    (value, None)
                } else {
                    (paying, Some(start_s + self.min_period_s))
                }
            }
        };
        self.current = Some(Scheduled {
            id: self.next_id,
            start_s,
            // Nothing turns behind a closed pin: what the profile asks meanwhile (a pin
            // opening the rate put off to the next line) is owed to that line.
            rpm: if pin_open {
                self.template.quantize(raw_rpm)
            } else {
                0.0
            },
            pin_open,
        });
        self.next_id += 1;
        self.next_start_s = next_start_s;
    }

    /// The commanded rpm at `t`.
    fn value_at(&self, t: f64) -> f64 {
        self.points
            .iter()
            .rposition(|p| p.plan_s <= t)
            .map_or(0.0, |i| self.value_on(i, t))
    }

    /// The rpm at `t` on the piece from command `i` to the next (held, or linear with a
    /// first-order hold; the last command held on).
    fn value_on(&self, i: usize, t: f64) -> f64 {
        let p = self.points[i];
        match (self.hold, self.points.get(i + 1)) {
            (Hold::FirstOrder, Some(n)) if n.plan_s > p.plan_s => {
                p.rpm + (n.rpm - p.rpm) * (t.min(n.plan_s) - p.plan_s) / (n.plan_s - p.plan_s)
            }
            _ => p.rpm,
        }
    }

    /// rpm·s commanded over `[a, b)` by the commands held here (0 before the first, the last
    /// held after it): exact, trapezoids on linear pieces.
    fn integral(&self, a: f64, b: f64) -> f64 {
        let mut sum = 0.0;
        for (i, p) in self.points.iter().enumerate() {
            let end = self.points.get(i + 1).map_or(f64::INFINITY, |n| n.plan_s);
            let (lo, hi) = (p.plan_s.max(a), end.min(b));
            if hi > lo {
                sum += 0.5 * (self.value_on(i, lo) + self.value_on(i, hi)) * (hi - lo);
            }
        }
        sum
    }
}

#[cfg(test)]
mod tests;
