//! The modal G-code machine: turns lexed lines into [`GcodeMove`]s in SI units.
//!
//! State follows Marlin: `G90`/`G91` set every axis including E absolute/relative, `M82`/`M83`
//! then override E alone; `G92` redefines the logical position without motion (its offsets are
//! kept, so published targets are always in the machine frame); `G28` homes the named axes (all
//! when none are named; X or Y homes both, as a polar machine must) and clears their offsets. Arcs (`G2`/`G3`, XY plane, `I`/`J` or `R`) are
//! split into chords whose sagitta stays within the chord tolerance.
//!
//! Commands with no effect on motion or material are ignored on purpose (temperatures, fans,
//! steppers on/off, messages, progress, limits meant for a firmware planner); see
//! [`IGNORED_M_CODES`]. Any other unknown command is a [`Warning`] with its line, never an error.

use polar_cell_msgs::GcodeMove;

use crate::error::{ErrorKind, GcodeError, Warning};
use crate::lexer::{LexError, Lexer, Word};

/// M-codes that do not move the machine nor change the material flow, so the streamer skips
/// them silently: temperatures (104, 109, 140, 190, 141, 191), fans (106, 107), steppers
/// (17, 18, 84), messages (117, 118), reports (105, 114, 115), progress (73), finish moves
/// (400), firmware-planner settings (201–205, 900), object labels (486), beep (300), and the
/// program-end codes 0, 1, 2, 30 (a streamed file simply ends).
pub const IGNORED_M_CODES: &[u32] = &[
    0, 1, 2, 17, 18, 30, 73, 84, 104, 105, 106, 107, 109, 114, 115, 117, 118, 140, 141, 190, 191,
    201, 202, 203, 204, 205, 300, 400, 486, 900,
];

/// Options of the interpreter; the defaults suit slicer output for the polar cell.
#[derive(Clone, Debug, PartialEq)]
pub struct InterpreterOptions {
    /// Largest distance between an arc and its chords (mm). Smaller means more chords.
    pub arc_tolerance_mm: f64,
    /// Feedrate used before the file sets any `F` (mm/min).
    pub default_feedrate_mm_per_min: f64,
    /// Where `G28` puts the homed axes, machine frame (mm).
    pub home_position_mm: [f64; 3],
    /// Where the tool stands before the first line, machine frame (mm): a print started
    /// where an earlier one stopped. A first move that names only some axes keeps the others
    /// here, and relative moves count from here.
    pub start_position_mm: [f64; 3],
    /// An arc needing more chords than this is rejected rather than flooding the pipeline.
    pub max_arc_segments: u32,
    /// Arc end radius may differ from the start radius by this much (mm) before it is an error;
    /// within it the radius is blended along the arc.
    pub arc_radius_mismatch_mm: f64,
}

impl Default for InterpreterOptions {
    fn default() -> Self {
        InterpreterOptions {
            arc_tolerance_mm: 0.002,
            default_feedrate_mm_per_min: 1500.0,
            home_position_mm: [0.0, 0.0, 0.0],
            start_position_mm: [0.0, 0.0, 0.0],
            max_arc_segments: 100_000,
            arc_radius_mismatch_mm: 0.05,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Plane {
    Xy,
    Zx,
    Yz,
}

/// Parameters of one command, indexed by letter.
#[derive(Clone, Copy)]
struct Params {
    values: [f64; 26],
    present: u32,
}

impl Params {
    fn new() -> Self {
        Params {
            values: [0.0; 26],
            present: 0,
        }
    }
    fn get(&self, letter: u8) -> Option<f64> {
        let i = (letter - b'A') as usize;
        (self.present & (1 << i) != 0).then(|| self.values[i])
    }
    fn has(&self, letter: u8) -> bool {
        self.present & (1 << (letter - b'A')) != 0
    }
}

/// The modal state machine. Feed it lines in order with [`Interpreter::feed_line`].
#[derive(Debug)]
pub struct Interpreter {
    options: InterpreterOptions,
    lexer: Lexer,
    file: String,
    /// Logical position (what the G-code means), mm; machine = logical + offset.
    logical_mm: [f64; 3],
    offset_mm: [f64; 3],
    e_mm: f64,
    feedrate_mm_per_min: f64,
    unit_mm: f64,
    relative_xyz: bool,
    relative_e: bool,
    plane: Plane,
    tool: u8,
    feedrate_percent: f64,
    flow_percent: f64,
    last_motion: Option<u32>,
    next_sequence: u64,
    /// The last `N` line number (or what `M110` set): a numbered line must follow it by one,
    /// as a firmware checks a host's stream, so a line lost between two numbered ones is an
    /// error, not a silent gap.
    last_numbered: Option<i64>,
}

/// Output of one line.
#[derive(Debug, Default)]
pub struct LineOutput {
    pub moves: Vec<GcodeMove>,
    pub warnings: Vec<Warning>,
}

impl Interpreter {
    pub fn new(file: impl Into<String>, options: InterpreterOptions) -> Self {
        let feedrate_mm_per_min = options.default_feedrate_mm_per_min;
        Interpreter {
            logical_mm: options.start_position_mm,
            options,
            lexer: Lexer::default(),
            file: file.into(),
            offset_mm: [0.0; 3],
            e_mm: 0.0,
            feedrate_mm_per_min,
            unit_mm: 1.0,
            relative_xyz: false,
            relative_e: false,
            plane: Plane::Xy,
            tool: 0,
            feedrate_percent: 100.0,
            flow_percent: 100.0,
            last_motion: None,
            next_sequence: 0,
            last_numbered: None,
        }
    }

    /// The sequence number the next move will get.
    pub fn next_sequence(&self) -> u64 {
        self.next_sequence
    }

    /// Machine position now (mm).
    pub fn machine_position_mm(&self) -> [f64; 3] {
        std::array::from_fn(|i| self.logical_mm[i] + self.offset_mm[i])
    }

    fn error(&self, line: u32, column: u32, kind: ErrorKind) -> GcodeError {
        GcodeError {
            file: self.file.clone(),
            line,
            column,
            kind,
        }
    }

    /// Interpret one line (1-based `line_number`, bytes without the line terminator), appending
    /// its moves and warnings to `out`. On error nothing of the line is applied.
    pub fn feed_line(
        &mut self,
        line_number: u32,
        bytes: &[u8],
        out: &mut LineOutput,
    ) -> Result<(), GcodeError> {
        // A file saved with a byte-order mark (Windows editors) starts with it.
        let bytes = match bytes.strip_prefix(b"\xEF\xBB\xBF") {
            Some(rest) if line_number == 1 => rest,
            _ => bytes,
        };
        let lexed = match self.lexer.lex(bytes) {
            Ok(l) => l,
            Err(LexError { column, kind }) => {
                // A line whose first word is not `letter number` is no command at all (e.g. a
                // stray text line): firmware answers "unknown command" and so do we.
                if let ErrorKind::ExpectedNumberAfter(_) = kind {
                    if first_word_column(bytes) == Some(column - 1) {
                        out.warnings.push(Warning {
                            line: line_number,
                            column: column - 1,
                            message: format!(
                                "unknown command `{}` ignored",
                                String::from_utf8_lossy(bytes).trim()
                            ),
                        });
                        return Ok(());
                    }
                }
                return Err(self.error(line_number, column, kind));
            }
        };
        // `M110` sets the number itself, whatever its line's own.
        let sets_number = lexed
            .words
            .first()
            .is_some_and(|w| w.letter == b'M' && w.value == 110.0);
        if let (Some(found), Some(last), false) =
            (lexed.line_number, self.last_numbered, sets_number)
        {
            if Some(found) != last.checked_add(1) {
                self.lexer.recycle(lexed);
                return Err(self.error(
                    line_number,
                    first_word_column(bytes).unwrap_or(1),
                    ErrorKind::LineNumberOutOfOrder {
                        expected: last.saturating_add(1),
                        found,
                    },
                ));
            }
        }
        let result = self.execute_words(line_number, &lexed.words, out);
        if result.is_ok() {
            // An `M110 N…` (its N checked by the command) sets the number, else the line's.
            let m110_n = lexed
                .words
                .iter()
                .find(|w| sets_number && w.letter == b'N')
                .map(|w| w.value as i64);
            if let Some(n) = m110_n.or(lexed.line_number) {
                self.last_numbered = Some(n);
            }
        }
        self.lexer.recycle(lexed);
        result
    }

    fn execute_words(
        &mut self,
        line: u32,
        words: &[Word],
        out: &mut LineOutput,
    ) -> Result<(), GcodeError> {
        let mut i = 0;
        while i < words.len() {
            let head = words[i];
            let (command, params_start) = match head.letter {
                b'G' | b'M' | b'T' => (head, i + 1),
                _ => match self.last_motion {
                    // A line of bare axis words repeats the last motion command (CNC modal).
                    Some(code) => (
                        Word {
                            letter: b'G',
                            value: code as f64,
                            column: head.column,
                        },
                        i,
                    ),
                    None => {
                        out.warnings.push(Warning {
                            line,
                            column: head.column,
                            message: format!(
                                "`{}` word with no command before it ignored",
                                head.letter as char
                            ),
                        });
                        return Ok(());
                    }
                },
            };
            // After an M code, `T` names a tool for it (`M104 S200 T1`, `M204 P1250 T1250`,
            // `M221 T0 S95`): a parameter, not a tool change.
            let ends_command = |letter: u8| match letter {
                b'G' | b'M' => true,
                b'T' => command.letter != b'M',
                _ => false,
            };
            let mut end = params_start;
            while end < words.len() && !ends_command(words[end].letter) {
                end += 1;
            }
            if command.value.is_nan() {
                return Err(self.error(
                    line,
                    command.column + 1,
                    ErrorKind::ExpectedNumberAfter(command.letter as char),
                ));
            }
            // `G28 X Y` homes the axes named; a command the streamer skips (`M84 X Y E`)
            // may have flags it does not read.
            let takes_flags = (command.letter == b'G' && command.value == 28.0)
                || !acts_on(command.letter, command.value);
            let mut params = Params::new();
            for w in &words[params_start..end] {
                if w.value.is_nan() && !takes_flags {
                    return Err(self.error(
                        line,
                        w.column + 1,
                        ErrorKind::ExpectedNumberAfter(w.letter as char),
                    ));
                }
                if w.value.is_infinite() || w.value.abs() > 1e12 {
                    return Err(self.error(
                        line,
                        w.column,
                        ErrorKind::OutOfRange {
                            letter: w.letter as char,
                            value: w.value,
                        },
                    ));
                }
                let bit = 1u32 << (w.letter - b'A');
                if params.present & bit != 0 {
                    return Err(self.error(
                        line,
                        w.column,
                        ErrorKind::DuplicateWord {
                            letter: w.letter as char,
                        },
                    ));
                }
                params.present |= bit;
                params.values[(w.letter - b'A') as usize] = w.value;
            }
            self.execute(line, command, &params, out)?;
            i = end;
        }
        Ok(())
    }

    fn execute(
        &mut self,
        line: u32,
        command: Word,
        p: &Params,
        out: &mut LineOutput,
    ) -> Result<(), GcodeError> {
        let code_f = command.value;
        let integer = code_f.fract() == 0.0 && (0.0..1e6).contains(&code_f);
        let code = code_f as u32;
        let name = || format!("{}{}", command.letter as char, code_f);
        let unknown = |out: &mut LineOutput| {
            out.warnings.push(Warning {
                line,
                column: command.column,
                message: format!("unknown command `{}` ignored", name()),
            })
        };
        if !integer {
            unknown(out);
            return Ok(());
        }
        match (command.letter, code) {
            (b'G', 0 | 1) => {
                self.last_motion = Some(code);
                self.linear(line, code, p, out, command.column)
            }
            (b'G', 2 | 3) => {
                self.last_motion = Some(code);
                self.arc(line, code == 2, p, out, command.column)
            }
            (b'G', 4) => {
                let seconds = match (p.get(b'P'), p.get(b'S')) {
                    (Some(ms), _) => ms / 1000.0,
                    (None, Some(s)) => s,
                    (None, None) => 0.0,
                };
                if seconds < 0.0 {
                    return Err(self.invalid(
                        line,
                        command.column,
                        name(),
                        "dwell time is negative",
                    ));
                }
                let mut m = self.base_move(line, GcodeMove::KIND_DWELL);
                m.dwell_s = seconds;
                self.push(out, m);
                Ok(())
            }
            (b'G', 17) => {
                self.plane = Plane::Xy;
                Ok(())
            }
            (b'G', 18) => {
                self.plane = Plane::Zx;
                Ok(())
            }
            (b'G', 19) => {
                self.plane = Plane::Yz;
                Ok(())
            }
            (b'G', 20) => {
                self.unit_mm = 25.4;
                Ok(())
            }
            (b'G', 21) => {
                self.unit_mm = 1.0;
                Ok(())
            }
            (b'G', 28) => {
                let named: Vec<usize> = (0..3).filter(|&i| p.has(b"XYZ"[i])).collect();
                let axes: Vec<usize> = if named.is_empty() {
                    vec![0, 1, 2]
                } else if named.contains(&0) || named.contains(&1) {
                    // Polar practice (Klipper's polar kinematics): X and Y are one mechanism
                    // (bed angle and arm radius), so homing either homes both.
                    let mut both = vec![0, 1];
                    both.extend(named.iter().filter(|&&a| a == 2));
                    both
                } else {
                    named
                };
                let mut mask = 0u8;
                for &a in &axes {
                    self.offset_mm[a] = 0.0;
                    self.logical_mm[a] = self.options.home_position_mm[a];
                    mask |= 1 << a;
                }
                let mut m = self.base_move(line, GcodeMove::KIND_HOME);
                m.axes = mask;
                self.push(out, m);
                Ok(())
            }
            (b'G', 90) => {
                self.relative_xyz = false;
                self.relative_e = false;
                Ok(())
            }
            (b'G', 91) => {
                self.relative_xyz = true;
                self.relative_e = true;
                Ok(())
            }
            (b'G', 92) => {
                let machine = self.machine_position_mm();
                let mut mask = 0u8;
                let all = !b"XYZE".iter().any(|&letter| p.has(letter));
                for (a, &letter) in b"XYZ".iter().enumerate() {
                    if all || p.has(letter) {
                        let value = p.get(letter).unwrap_or(0.0) * self.unit_mm;
                        self.logical_mm[a] = value;
                        self.offset_mm[a] = machine[a] - value;
                        mask |= 1 << a;
                    }
                }
                if all || p.has(b'E') {
                    self.e_mm = p.get(b'E').unwrap_or(0.0) * self.unit_mm;
                    mask |= GcodeMove::AXIS_E;
                }
                let mut m = self.base_move(line, GcodeMove::KIND_SET_POSITION);
                m.axes = mask;
                self.push(out, m);
                Ok(())
            }
            (b'M', 82) => {
                self.relative_e = false;
                Ok(())
            }
            (b'M', 110) => {
                // Sets the line number (in `feed_line`, once the line is done): checked here.
                match p.get(b'N') {
                    Some(n) if n.fract() != 0.0 || !(0.0..=i64::MAX as f64 / 2.0).contains(&n) => {
                        Err(self.invalid(
                            line,
                            command.column,
                            name(),
                            "N must be a whole number from 0",
                        ))
                    }
                    _ => Ok(()),
                }
            }
            (b'M', 83) => {
                self.relative_e = true;
                Ok(())
            }
            (b'M', 220) => {
                if let Some(s) = p.get(b'S') {
                    if s <= 0.0 {
                        return Err(self.invalid(line, command.column, name(), "S must be > 0"));
                    }
                    self.feedrate_percent = s;
                }
                Ok(())
            }
            (b'M', 221) => {
                // The cell has one screw: a factor for another tool is not this one's.
                if let Some(tool) = p.get(b'T').filter(|&t| t != self.tool as f64) {
                    out.warnings.push(Warning {
                        line,
                        column: command.column,
                        message: format!(
                            "{} for tool {tool} ignored: the current tool is {}",
                            name(),
                            self.tool
                        ),
                    });
                    return Ok(());
                }
                if let Some(s) = p.get(b'S') {
                    if s < 0.0 {
                        return Err(self.invalid(line, command.column, name(), "S must be >= 0"));
                    }
                    self.flow_percent = s;
                }
                Ok(())
            }
            (b'M', c) if IGNORED_M_CODES.contains(&c) => Ok(()),
            (b'T', t) => {
                if t > 255 {
                    return Err(self.invalid(
                        line,
                        command.column,
                        name(),
                        "tool number above 255",
                    ));
                }
                self.tool = t as u8;
                Ok(())
            }
            _ => {
                unknown(out);
                Ok(())
            }
        }
    }

    fn invalid(
        &self,
        line: u32,
        column: u32,
        command: String,
        problem: &'static str,
    ) -> GcodeError {
        self.error(line, column, ErrorKind::InvalidCommand { command, problem })
    }

    fn set_feedrate(&mut self, line: u32, p: &Params, column: u32) -> Result<(), GcodeError> {
        if let Some(f) = p.get(b'F') {
            if f <= 0.0 {
                return Err(self.invalid(line, column, "F".into(), "feedrate must be > 0"));
            }
            self.feedrate_mm_per_min = f * self.unit_mm;
        }
        Ok(())
    }

    /// Logical XYZ target of a motion command.
    fn target_logical(&self, p: &Params) -> [f64; 3] {
        std::array::from_fn(|a| match p.get(b"XYZ"[a]) {
            Some(v) if self.relative_xyz => self.logical_mm[a] + v * self.unit_mm,
            Some(v) => v * self.unit_mm,
            None => self.logical_mm[a],
        })
    }

    fn target_e(&self, p: &Params) -> f64 {
        match p.get(b'E') {
            Some(v) if self.relative_e => self.e_mm + v * self.unit_mm,
            Some(v) => v * self.unit_mm,
            None => self.e_mm,
        }
    }

    fn linear(
        &mut self,
        line: u32,
        code: u32,
        p: &Params,
        out: &mut LineOutput,
        column: u32,
    ) -> Result<(), GcodeError> {
        self.set_feedrate(line, p, column)?;
        let target = self.target_logical(p);
        let e = self.target_e(p);
        let kind = if code == 0 {
            GcodeMove::KIND_RAPID
        } else {
            GcodeMove::KIND_LINEAR
        };
        self.emit_motion(line, kind, target, e, 0, 1, out);
        Ok(())
    }

    #[allow(clippy::too_many_arguments)]
    fn emit_motion(
        &mut self,
        line: u32,
        kind: u8,
        target_logical: [f64; 3],
        e_mm: f64,
        segment_index: u32,
        segment_count: u32,
        out: &mut LineOutput,
    ) {
        let delta_e_mm = (e_mm - self.e_mm) * self.flow_percent / 100.0;
        self.logical_mm = target_logical;
        self.e_mm = e_mm;
        let mut m = self.base_move(line, kind);
        m.delta_e_m = delta_e_mm / 1000.0;
        m.extrude = delta_e_mm > 0.0;
        m.segment_index = segment_index;
        m.segment_count = segment_count;
        self.push(out, m);
    }

    fn base_move(&self, line: u32, kind: u8) -> GcodeMove {
        let machine = self.machine_position_mm();
        GcodeMove {
            sequence: 0,
            source_line: line,
            kind,
            segment_index: 0,
            segment_count: 1,
            x_m: machine[0] / 1000.0,
            y_m: machine[1] / 1000.0,
            z_m: machine[2] / 1000.0,
            e_m: self.e_mm / 1000.0,
            delta_e_m: 0.0,
            feedrate_m_per_s: self.feedrate_mm_per_min * self.feedrate_percent / 100.0 / 60_000.0,
            extrude: false,
            dwell_s: 0.0,
            axes: 0,
            tool: self.tool,
        }
    }

    fn push(&mut self, out: &mut LineOutput, mut m: GcodeMove) {
        m.sequence = self.next_sequence;
        self.next_sequence += 1;
        out.moves.push(m);
    }

    fn arc(
        &mut self,
        line: u32,
        clockwise: bool,
        p: &Params,
        out: &mut LineOutput,
        column: u32,
    ) -> Result<(), GcodeError> {
        let file = self.file.clone();
        let arc_error = |s: String| GcodeError {
            file: file.clone(),
            line,
            column,
            kind: ErrorKind::InvalidArc(s),
        };
        if self.plane != Plane::Xy {
            return Err(arc_error(
                "only arcs in the XY plane (G17) are supported".into(),
            ));
        }
        self.set_feedrate(line, p, column)?;
        let start = self.logical_mm;
        let end = self.target_logical(p);
        let e_end = self.target_e(p);
        let (sx, sy) = (start[0], start[1]);
        let (ex, ey) = (end[0], end[1]);
        let has_ij = p.has(b'I') || p.has(b'J');
        let (cx, cy) = match (has_ij, p.get(b'R')) {
            (true, Some(_)) => return Err(arc_error("give either I/J or R, not both".into())),
            (false, None) => {
                return Err(arc_error("needs I/J (centre offset) or R (radius)".into()))
            }
            (true, None) => (
                sx + p.get(b'I').unwrap_or(0.0) * self.unit_mm,
                sy + p.get(b'J').unwrap_or(0.0) * self.unit_mm,
            ),
            (false, Some(r)) => {
                let r = r * self.unit_mm;
                let (dx, dy) = (ex - sx, ey - sy);
                let d = dx.hypot(dy);
                if d == 0.0 {
                    return Err(arc_error(
                        "an R arc needs an end point different from its start".into(),
                    ));
                }
                let h2 = r * r - d * d / 4.0;
                let tolerance = self.options.arc_radius_mismatch_mm;
                if h2 < 0.0 && r.abs() + tolerance < d / 2.0 {
                    return Err(arc_error(format!(
                        "radius {:.4} mm is smaller than half the chord ({:.4} mm)",
                        r.abs(),
                        d / 2.0
                    )));
                }
                let h = h2.max(0.0).sqrt();
                // Centre to the right of the chord for a short clockwise arc, to the left for a
                // short counter-clockwise one; a negative R asks for the long arc.
                let side = if clockwise == (r > 0.0) { -1.0 } else { 1.0 };
                let (nx, ny) = (-dy / d, dx / d);
                (
                    (sx + ex) / 2.0 + side * h * nx,
                    (sy + ey) / 2.0 + side * h * ny,
                )
            }
        };
        let r0 = (sx - cx).hypot(sy - cy);
        let r1 = (ex - cx).hypot(ey - cy);
        if r0 == 0.0 {
            return Err(arc_error("centre coincides with the start point".into()));
        }
        if (r0 - r1).abs() > self.options.arc_radius_mismatch_mm {
            return Err(arc_error(format!(
                "start radius {r0:.4} mm and end radius {r1:.4} mm differ"
            )));
        }
        let a0 = (sy - cy).atan2(sx - cx);
        let a1 = (ey - cy).atan2(ex - cx);
        let tau = std::f64::consts::TAU;
        let same_point = (ex - sx).hypot(ey - sy) < 1e-9;
        // An arc back to its start is a full circle. Its two angles may still differ by a
        // whole turn (atan2 answers +π or -π for a start at -0.0 or a hair below the
        // centre's Y), so the sweep is set, not corrected.
        let mut sweep = match (same_point, clockwise) {
            (true, true) => -tau,
            (true, false) => tau,
            (false, _) => a1 - a0,
        };
        if !same_point {
            if clockwise && sweep >= 0.0 {
                sweep -= tau;
            } else if !clockwise && sweep <= 0.0 {
                sweep += tau;
            }
        }
        if let Some(turns) = p.get(b'P') {
            if turns.fract() != 0.0 || turns < 1.0 {
                return Err(arc_error("P (turns) must be a whole number >= 1".into()));
            }
            sweep += sweep.signum() * tau * (turns - 1.0);
        }
        let r_max = r0.max(r1);
        let tol = self.options.arc_tolerance_mm;
        let max_step = if tol >= r_max {
            std::f64::consts::PI
        } else {
            2.0 * (1.0 - tol / r_max).acos()
        };
        let segments_f = (sweep.abs() / max_step).ceil().max(1.0);
        if segments_f > self.options.max_arc_segments as f64 {
            return Err(arc_error(format!(
                "needs {segments_f} chords for the {tol} mm chord tolerance (limit {})",
                self.options.max_arc_segments
            )));
        }
        let n = segments_f as u32;
        let kind = if clockwise {
            GcodeMove::KIND_ARC_CW
        } else {
            GcodeMove::KIND_ARC_CCW
        };
        let e0 = self.e_mm;
        for i in 1..=n {
            let f = i as f64 / n as f64;
            let target = if i == n {
                end
            } else {
                let a = a0 + sweep * f;
                let r = r0 + (r1 - r0) * f;
                [
                    cx + r * a.cos(),
                    cy + r * a.sin(),
                    start[2] + (end[2] - start[2]) * f,
                ]
            };
            let e = if i == n { e_end } else { e0 + (e_end - e0) * f };
            self.emit_motion(line, kind, target, e, i - 1, n, out);
        }
        Ok(())
    }
}

/// Whether the interpreter acts on `letter code` (the commands of [`Interpreter::execute`]):
/// their parameters must be numbers (bar `G28`'s flags). Every other command is skipped or
/// warned about, so a flag word among its parameters is no error.
fn acts_on(letter: u8, code: f64) -> bool {
    code.fract() == 0.0
        && (0.0..1e6).contains(&code)
        && matches!(
            (letter, code as u32),
            (b'G', 0..=4 | 17..=21 | 28 | 90..=92) | (b'M', 82 | 83 | 110 | 220 | 221) | (b'T', _)
        )
}

/// 0-based column of the first non-blank byte, if the line has one before any comment.
fn first_word_column(bytes: &[u8]) -> Option<u32> {
    let i = bytes.iter().position(|&b| b != b' ' && b != b'\t')?;
    (bytes[i].is_ascii_alphabetic()).then_some(i as u32 + 1)
}
