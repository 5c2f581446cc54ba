//! The lookahead planner: `GcodeMove`s in, timed joint trajectories out.
//!
//! Each move becomes one or more blocks: a *path* block (a line, split into nodes), a *fixed*
//! block (a rotation of the bed at the centre, a dwell, an extruder-only move — the stage is at
//! rest before and after), or a *marker* (no motion: G92). Path blocks queue up to the
//! lookahead; their speeds are planned together so corners are taken without stopping, with
//! the queue always able to stop at its end. When the queue is full its first half is
//! emitted; a fixed block flushes everything before it.
//!
//! At the centre θ is undefined. A line whose support passes within `center_radius` of the
//! centre (inside the segment) is taken through the centre itself — the path then deviates
//! from the commanded line by at most that radius. Without negative radii the stage stops at
//! the centre, the bed turns by π, and the arm goes on; with them the arm crosses the centre
//! with θ held. A move starting at the centre first turns the bed to the move's heading.

use std::collections::VecDeque;

use polar_cell_msgs::GcodeMove;

use crate::path::{continuous_theta, subdivide, Joints, Line, PathNode};
use crate::timing::{plan_speeds, JointLimits, SpeedLimits, SpeedNode};

/// Joint order everywhere: bed, arm, z.
pub const JOINT_NAMES: [&str; 3] = ["bed_theta", "arm_r", "z"];

/// The slowest feed planned (0.06 mm/min). With [`MAX_REST_S`] it keeps every move's
/// duration within about 10⁶ s, so plan time never overflows (a subnormal feed made it ∞).
pub const MIN_FEED_M_PER_S: f64 = 1e-6;

/// How far past a position limit a start position may lie (m): half a step of a fine
/// stepper, so a machine stopped at a limit (its position read from whole steps) can start
/// again from there.
pub const INITIAL_SLACK: f64 = 1e-5;

/// The longest dwell or extruder-only rest planned, s (about 11.6 days).
pub const MAX_REST_S: f64 = 1e6;

/// Planner settings; defaults match `urdf/polar_cell.urdf`.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannerOptions {
    /// Largest distance of the executed joint path from the commanded line (m).
    pub path_tolerance_m: f64,
    /// Lines passing closer than this to the centre are taken through it (m).
    pub center_radius_m: f64,
    /// Let the arm cross the centre with a negative radius instead of turning the bed.
    pub allow_negative_r: bool,
    /// Limits of `bed_theta`, `arm_r`, `z`.
    pub joints: [JointLimits; 3],
    /// Tangential acceleration of the tool (m/s²).
    pub max_tool_acceleration_m_per_s2: f64,
    /// Nodes at least this close along a line, so the speed profile is sampled finely (m).
    pub max_node_spacing_m: f64,
    /// Path blocks planned together.
    pub lookahead_blocks: usize,
    /// Speed of G28 homing moves (m/s).
    pub homing_speed_m_per_s: f64,
    /// Fraction of each acceleration limit the planner uses (the rest covers the variation of
    /// the path's curvature between nodes).
    pub acceleration_safety: f64,
    /// Joint position at start-up.
    pub initial_joints: Joints,
    /// Rest this long before each extruding move that follows a non-extruding one, for the
    /// extruder's pin to open (screw_driver's `stop` strategy; 0: never).
    pub pin_open_dwell_s: f64,
    /// What the screw can feed: extruding moves are slowed so their material never needs more
    /// rpm than this (`None`: the plan ignores the screw).
    pub screw: Option<ScrewLimits>,
}

/// The screw as the planner must respect it (like Klipper's toolhead checks its extruder).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScrewLimits {
    /// rpm the plan may use: the screw's maximum less the headroom its flow compensation needs.
    pub usable_rpm: f64,
    /// Filament-equivalent length one revolution feeds (m), as the screw driver's model.
    pub e_per_rev_m: f64,
    /// Time constant of the delivered flow (the screw driver's `flow_tau_s`): a prime gets
    /// time for the flow to rise and to drain before the stage moves on.
    pub flow_tau_s: f64,
}

impl ScrewLimits {
    /// Fastest tool speed (m/s) at which a move feeding `delta_e_m` over `length_m` stays
    /// within the usable rpm: rpm = 60·v·(ΔE/L)/e_rev.
    pub fn max_speed(&self, delta_e_m: f64, length_m: f64) -> f64 {
        if delta_e_m <= 0.0 || length_m <= 0.0 {
            return f64::INFINITY;
        }
        self.usable_rpm * self.e_per_rev_m * length_m / (60.0 * delta_e_m)
    }

    /// Shortest time (s) in which the screw can feed `delta_e_m` in place (a prime): the
    /// material at the usable rpm, plus five time constants of the flow, for it to rise and
    /// to drain to under 1 % before the next move.
    pub fn min_duration(&self, delta_e_m: f64) -> f64 {
        if delta_e_m <= 0.0 {
            return 0.0;
        }
        60.0 * delta_e_m / (self.usable_rpm * self.e_per_rev_m) + 5.0 * self.flow_tau_s
    }
}

impl Default for PlannerOptions {
    fn default() -> Self {
        PlannerOptions {
            path_tolerance_m: 5e-6,
            center_radius_m: 1e-6,
            allow_negative_r: false,
            joints: [
                JointLimits {
                    velocity: 6.0,
                    acceleration: 40.0,
                    velocity_jump: 0.1,
                    position: None,
                },
                JointLimits {
                    velocity: 0.2,
                    acceleration: 3.0,
                    velocity_jump: 0.01,
                    position: Some((0.0, 0.15)),
                },
                JointLimits {
                    velocity: 0.02,
                    acceleration: 0.5,
                    velocity_jump: 0.002,
                    position: Some((0.0, 0.3)),
                },
            ],
            max_tool_acceleration_m_per_s2: 3.0,
            max_node_spacing_m: 0.002,
            lookahead_blocks: 64,
            homing_speed_m_per_s: 0.05,
            acceleration_safety: 0.9,
            initial_joints: [0.0, 0.0, 0.0],
            pin_open_dwell_s: 0.0,
            screw: None,
        }
    }
}

/// A planned instant: joints, their rates, and the Cartesian tool speed.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct TrajPoint {
    /// Plan time (s from the start of planning).
    pub t: f64,
    pub q: Joints,
    pub qd: Joints,
    pub qdd: Joints,
    /// True Cartesian tool speed |ṗ| (m/s), from the planned path speed.
    pub tool_speed: f64,
}

/// The plan of one `GcodeMove`.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct PlannedMove {
    pub sequence: u64,
    pub source_line: u32,
    pub kind: u8,
    /// Commanded Cartesian length (m) and extruder change (m) of the move.
    pub length_m: f64,
    pub delta_e_m: f64,
    pub extrude: bool,
    /// At least one point; consecutive points with a path between them; a corner between two
    /// moves repeats the time with the velocity jump.
    pub points: Vec<TrajPoint>,
    /// How much slower than commanded the screw's limit made this move (feed or, for a
    /// prime, duration ratio > 1); `None` when the screw did not limit it.
    pub slowed_for_screw: Option<f64>,
    /// Where planning stood once this move was emitted ([`Planner::resume`]).
    pub resume: ResumePoint,
}

/// Where planning stands at the end of an emitted move: everything a planner in a new
/// process needs to plan the moves after it on the same timeline ([`Planner::resume`]).
///
/// Resumed there and fed the same moves, a planner emits what this one would have, bit for
/// bit, when this move ended a batch of emitted blocks — which is where a node acknowledges
/// (it acknowledges what it published). One that ended mid-batch continues from the same
/// state and speed with a lookahead of its own: another valid plan of the same path.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct ResumePoint {
    /// Plan time at the end of the move (s).
    pub t_s: f64,
    /// Path speed² there (m²/s²): the speed the next move starts with.
    pub path_speed2: f64,
    /// Joints after the move, as the next move's path starts from them (θ unwrapped).
    pub q: Joints,
    /// Commanded Cartesian position after the move (m).
    pub p_m: [f64; 3],
    /// The last emitted point (a marker repeats it).
    pub last_point: TrajPoint,
    /// Whether the last motion move fed material (for the pin dwell).
    pub previous_extruding: bool,
}

impl PlannedMove {
    pub fn start_time(&self) -> f64 {
        self.points.first().map_or(0.0, |p| p.t)
    }
    pub fn end_time(&self) -> f64 {
        self.points.last().map_or(0.0, |p| p.t)
    }
}

/// Why a move cannot be planned.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanError {
    #[error(
        "move {sequence} (line {line}): {joint} would reach {value:.6}, outside [{min}, {max}]"
    )]
    OutOfRange {
        sequence: u64,
        line: u32,
        joint: &'static str,
        value: f64,
        min: f64,
        max: f64,
    },
    #[error("move {sequence} (line {line}): feedrate {feed} m/s is below the 1e-6 m/s the planner accepts")]
    BadFeedrate { sequence: u64, line: u32, feed: f64 },
    #[error("move {sequence} (line {line}): a rest of {seconds} s is longer than the 1e6 s the planner accepts")]
    RestTooLong {
        sequence: u64,
        line: u32,
        seconds: f64,
    },
    #[error("move {sequence} (line {line}): unknown move kind {kind}")]
    UnknownKind { sequence: u64, line: u32, kind: u8 },
    #[error("move {sequence} (line {line}): {field} is {value}, not a finite number")]
    NotFinite {
        sequence: u64,
        line: u32,
        field: &'static str,
        value: f64,
    },
    #[error("invalid planner option: {0}")]
    Options(String),
}

#[derive(Clone, Debug)]
enum BlockKind {
    Path {
        feed: f64,
        nodes: Vec<PathNode>,
        /// Where |θ'| = |c|/|p|² peaks (closest approach to the centre) and its value; the
        /// nodes around it are capped with it so the bed's speed holds between nodes too.
        theta_rate_peak: Option<(f64, f64)>,
    },
    /// Precomputed points relative to the block start (t from 0), at rest at both ends.
    Fixed {
        points: Vec<TrajPoint>,
    },
    Marker,
}

#[derive(Clone, Debug)]
struct Block {
    kind: BlockKind,
    /// Index into the pending moves.
    sequence: u64,
    last_of_move: bool,
}

/// The queue-side state after a move's last block was queued (for its [`ResumePoint`]).
#[derive(Clone, Copy, Debug)]
struct MoveEnd {
    sequence: u64,
    q: Joints,
    p_m: [f64; 3],
    previous_extruding: bool,
}

/// The streaming planner. Feed moves with [`Planner::push`], finish with [`Planner::flush`].
pub struct Planner {
    options: PlannerOptions,
    limits: SpeedLimits,
    /// Joints at the end of everything queued.
    q_end: Joints,
    /// Cartesian position at the end of everything queued.
    p_end: [f64; 3],
    queue: VecDeque<Block>,
    /// Moves whose blocks are queued or partly emitted, in order.
    moves: VecDeque<PlannedMove>,
    /// Plan time and state at the head of the queue.
    t_head: f64,
    v2_head: f64,
    scratch_s: Vec<f64>,
    scratch_nodes: Vec<SpeedNode>,
    scratch_v2: Vec<f64>,
    path_blocks_queued: usize,
    /// The last emitted point: a marker is an instant of the motion going on there.
    last_emitted: TrajPoint,
    /// Whether the last motion move fed material (for the pin dwell).
    previous_extruding: bool,
    /// For each move with blocks queued, in order: the state after its last block.
    move_ends: VecDeque<MoveEnd>,
}

impl Planner {
    pub fn new(options: PlannerOptions) -> Result<Self, PlanError> {
        let o = &options;
        if o.path_tolerance_m.is_nan()
            || o.path_tolerance_m <= 0.0
            || o.center_radius_m.is_nan()
            || o.center_radius_m < 0.0
        {
            return Err(PlanError::Options(
                "path_tolerance_m must be > 0, center_radius_m >= 0".into(),
            ));
        }
        if o.center_radius_m > o.path_tolerance_m {
            return Err(PlanError::Options(format!(
                "center_radius_m ({}) must not exceed path_tolerance_m ({}): the detour through the centre would leave the tolerance",
                o.center_radius_m, o.path_tolerance_m
            )));
        }
        for (name, j) in JOINT_NAMES.iter().zip(&o.joints) {
            if !(j.velocity > 0.0 && j.acceleration > 0.0 && j.velocity_jump >= 0.0) {
                return Err(PlanError::Options(format!(
                    "{name}: velocity and acceleration limits must be > 0 and the velocity jump >= 0, got velocity {}, acceleration {}, jump {}",
                    j.velocity, j.acceleration, j.velocity_jump
                )));
            }
        }
        if o.allow_negative_r {
            // Crossing the centre takes the arm to -r: it must reach as far on that side.
            if let Some((lower, upper)) = o.joints[1].position {
                if lower > -upper {
                    return Err(PlanError::Options(format!(
                        "allow_negative_r needs an arm that reaches as far on both sides of the centre, but {}'s limits are [{lower}, {upper}]",
                        JOINT_NAMES[1]
                    )));
                }
            }
        }
        if !(o.acceleration_safety > 0.0 && o.acceleration_safety <= 1.0) || o.lookahead_blocks < 2
        {
            return Err(PlanError::Options(
                "acceleration_safety in (0, 1], lookahead_blocks >= 2".into(),
            ));
        }
        for (j, &q) in o.initial_joints.iter().enumerate() {
            let (min, max) = position_range(o, j);
            // A stop position computed from steps may sit a rounding past a limit it reached.
            if !q.is_finite() || q < min - INITIAL_SLACK || q > max + INITIAL_SLACK {
                return Err(PlanError::Options(format!(
                    "initial position of {} is {q}, outside [{min}, {max}]",
                    JOINT_NAMES[j]
                )));
            }
        }
        if let Some(screw) = o.screw {
            if !(screw.usable_rpm.is_finite()
                && screw.usable_rpm > 0.0
                && screw.e_per_rev_m.is_finite()
                && screw.e_per_rev_m > 0.0
                && screw.flow_tau_s.is_finite()
                && screw.flow_tau_s >= 0.0)
            {
                return Err(PlanError::Options(format!(
                    "screw limits must be finite, rpm and e_per_rev > 0, flow τ >= 0: usable_rpm {}, e_per_rev_m {}, flow_tau_s {}",
                    screw.usable_rpm, screw.e_per_rev_m, screw.flow_tau_s
                )));
            }
        }
        let safety = o.acceleration_safety;
        let limits = SpeedLimits {
            joint_velocity: [
                o.joints[0].velocity,
                o.joints[1].velocity,
                o.joints[2].velocity,
            ],
            joint_acceleration: [
                o.joints[0].acceleration * safety,
                o.joints[1].acceleration * safety,
                o.joints[2].acceleration * safety,
            ],
            tool_acceleration: o.max_tool_acceleration_m_per_s2,
        };
        let q0 = start_joints(o);
        Ok(Planner {
            limits,
            q_end: q0,
            p_end: crate::path::forward(q0),
            options,
            queue: VecDeque::new(),
            moves: VecDeque::new(),
            t_head: 0.0,
            v2_head: 0.0,
            scratch_s: Vec::new(),
            scratch_nodes: Vec::new(),
            scratch_v2: Vec::new(),
            path_blocks_queued: 0,
            last_emitted: TrajPoint {
                q: q0,
                ..TrajPoint::default()
            },
            previous_extruding: false,
            move_ends: VecDeque::new(),
        })
    }

    /// Where a new planner with `options` starts: resumed there, a planner is a new one.
    pub fn start_point(options: &PlannerOptions) -> ResumePoint {
        let q0 = start_joints(options);
        ResumePoint {
            t_s: 0.0,
            path_speed2: 0.0,
            q: q0,
            p_m: crate::path::forward(q0),
            last_point: TrajPoint {
                q: q0,
                ..TrajPoint::default()
            },
            previous_extruding: false,
        }
    }

    /// A planner that continues where another one stood after emitting a move (its
    /// [`PlannedMove::resume`]): fed the moves after that one, it plans them on the same
    /// timeline, from the same joints and speed. `options` must be the other one's.
    pub fn resume(options: PlannerOptions, at: &ResumePoint) -> Result<Self, PlanError> {
        let finite = at.t_s.is_finite()
            && at.t_s >= 0.0
            && at.path_speed2.is_finite()
            && at.path_speed2 >= 0.0
            && at.q.iter().chain(&at.p_m).all(|x| x.is_finite());
        if !finite {
            return Err(PlanError::Options(format!(
                "resume point needs finite values, t >= 0 and speed² >= 0: {at:?}"
            )));
        }
        let mut planner = Planner::new(PlannerOptions {
            initial_joints: at.q,
            ..options
        })?;
        planner.p_end = at.p_m;
        planner.t_head = at.t_s;
        planner.v2_head = at.path_speed2;
        planner.last_emitted = at.last_point;
        planner.previous_extruding = at.previous_extruding;
        Ok(planner)
    }

    pub fn options(&self) -> &PlannerOptions {
        &self.options
    }

    /// Plan time at which everything emitted so far ends.
    pub fn time_emitted(&self) -> f64 {
        self.t_head
    }

    /// Queue one move; finished plans are appended to `out` in move order.
    pub fn push(&mut self, m: &GcodeMove, out: &mut Vec<PlannedMove>) -> Result<(), PlanError> {
        // Our streamer never sends a non-finite number, but any DDS publisher (or a bag) can.
        let fields = [
            ("x_m", m.x_m),
            ("y_m", m.y_m),
            ("z_m", m.z_m),
            ("delta_e_m", m.delta_e_m),
            ("feedrate_m_per_s", m.feedrate_m_per_s),
            ("dwell_s", m.dwell_s),
        ];
        if let Some(&(field, value)) = fields.iter().find(|(_, v)| !v.is_finite()) {
            return Err(PlanError::NotFinite {
                sequence: m.sequence,
                line: m.source_line,
                field,
                value,
            });
        }
        if m.kind > GcodeMove::KIND_SET_POSITION {
            return Err(PlanError::UnknownKind {
                sequence: m.sequence,
                line: m.source_line,
                kind: m.kind,
            });
        }
        if m.kind == GcodeMove::KIND_DWELL && m.dwell_s > MAX_REST_S {
            return Err(PlanError::RestTooLong {
                sequence: m.sequence,
                line: m.source_line,
                seconds: m.dwell_s,
            });
        }
        let target = [m.x_m, m.y_m, m.z_m];
        let length = crate::path::dist3(self.p_end, target);
        self.moves.push_back(PlannedMove {
            sequence: m.sequence,
            source_line: m.source_line,
            kind: m.kind,
            length_m: length,
            delta_e_m: m.delta_e_m,
            extrude: m.extrude,
            points: Vec::new(),
            slowed_for_screw: None,
            resume: ResumePoint::default(),
        });
        let seq = m.sequence;
        let moves_or_feeds = matches!(
            m.kind,
            GcodeMove::KIND_RAPID
                | GcodeMove::KIND_LINEAR
                | GcodeMove::KIND_ARC_CW
                | GcodeMove::KIND_ARC_CCW
        );
        // A move goes somewhere at a feed: both checked before anything of it is emitted
        // (a refused move must leave no pin-open dwell behind, nor the pin state changed).
        let goes = !matches!(m.kind, GcodeMove::KIND_DWELL | GcodeMove::KIND_SET_POSITION);
        let feed = if m.kind == GcodeMove::KIND_HOME {
            self.options.homing_speed_m_per_s
        } else {
            m.feedrate_m_per_s
        };
        if goes && (feed.is_nan() || feed < MIN_FEED_M_PER_S) {
            self.moves.pop_back();
            return Err(PlanError::BadFeedrate {
                sequence: seq,
                line: m.source_line,
                feed,
            });
        }
        if goes {
            if let Err(e) = self.check_range(m, target) {
                self.moves.pop_back();
                return Err(e);
            }
        }
        let feeds = m.extrude && m.delta_e_m > 0.0;
        let screw = self.options.screw.filter(|_| feeds);
        // An extruder-only move (retract, prime) rests for the E motion, at least as long as
        // the screw needs to feed it: its length is checked here too.
        let rest_s = (goes && length < GcodeMove::NO_PATH_M && m.delta_e_m != 0.0).then(|| {
            let duration = m.delta_e_m.abs() / feed;
            let needed = screw.map_or(0.0, |screw| screw.min_duration(m.delta_e_m));
            duration.max(needed)
        });
        if let Some(seconds) = rest_s.filter(|&s| s > MAX_REST_S) {
            self.moves.pop_back();
            return Err(PlanError::RestTooLong {
                sequence: seq,
                line: m.source_line,
                seconds,
            });
        }
        if moves_or_feeds
            && m.extrude
            && !self.previous_extruding
            && self.options.pin_open_dwell_s > 0.0
        {
            let rest = self.rest_points(self.options.pin_open_dwell_s);
            self.push_fixed(seq, rest, false, out);
        }
        // A line that neither goes anywhere nor moves E (`G1 F1800` between two extruding
        // moves) takes no time: the screw driver leaves the pin as it is over it, and so
        // must the dwell (it rested the stage with the pin open and the screw stopped).
        if moves_or_feeds && (length >= GcodeMove::NO_PATH_M || m.delta_e_m != 0.0) {
            self.previous_extruding = m.extrude;
        }
        match m.kind {
            GcodeMove::KIND_DWELL => {
                self.push_fixed(seq, self.rest_points(m.dwell_s.max(0.0)), true, out);
            }
            GcodeMove::KIND_SET_POSITION => self.push_block(
                Block {
                    kind: BlockKind::Marker,
                    sequence: seq,
                    last_of_move: true,
                },
                out,
            ),
            _ => {
                if length < GcodeMove::NO_PATH_M {
                    if let Some(duration) = rest_s {
                        let unslowed = m.delta_e_m.abs() / feed;
                        if duration > unslowed {
                            self.note_slowdown(duration / unslowed);
                        }
                        self.push_fixed(seq, self.rest_points(duration), true, out);
                    } else {
                        self.push_block(
                            Block {
                                kind: BlockKind::Marker,
                                sequence: seq,
                                last_of_move: true,
                            },
                            out,
                        );
                    }
                } else {
                    let mut feed = feed;
                    if let Some(screw) = screw {
                        let fastest = screw.max_speed(m.delta_e_m, length);
                        if fastest < feed {
                            self.note_slowdown(feed / fastest);
                            feed = fastest.max(MIN_FEED_M_PER_S);
                        }
                    }
                    self.push_line(seq, target, feed, out);
                }
            }
        }
        Ok(())
    }

    /// Record on the move just queued that the screw slowed it by `factor`.
    fn note_slowdown(&mut self, factor: f64) {
        if let Some(m) = self.moves.back_mut() {
            m.slowed_for_screw = Some(factor);
        }
    }

    /// Plan and emit everything queued, ending at rest.
    pub fn flush(&mut self, out: &mut Vec<PlannedMove>) {
        let n = self.queue.len();
        self.emit(n, out);
    }

    /// The target's radius and z within their limits, and, where the arm cannot reach the
    /// centre (a lower limit above 0), the radius all along the line: a line passing the
    /// centre dips below both of its ends. (A disc is convex: the ends bound the top; z
    /// runs linearly.)
    fn check_range(&self, m: &GcodeMove, target: [f64; 3]) -> Result<(), PlanError> {
        let r = target[0].hypot(target[1]);
        let nearest_r = self.nearest_radius(target);
        for (j, value) in [(1usize, r), (1usize, nearest_r), (2usize, target[2])] {
            if self.options.joints[j].position.is_none() {
                continue;
            }
            // (With negative radii allowed the arm's range is symmetric: checked in `new`.)
            let (min, max) = position_range(&self.options, j);
            if value < min - 1e-12 || value > max + 1e-12 {
                return Err(PlanError::OutOfRange {
                    sequence: m.sequence,
                    line: m.source_line,
                    joint: JOINT_NAMES[j],
                    value,
                    min,
                    max,
                });
            }
        }
        Ok(())
    }

    /// The smallest radius on the line from here to `target` (0 through the centre zone,
    /// where the planner goes through the centre itself).
    fn nearest_radius(&self, target: [f64; 3]) -> f64 {
        let a = self.p_end;
        let ab = [target[0] - a[0], target[1] - a[1]];
        let len2 = ab[0] * ab[0] + ab[1] * ab[1];
        let r_end = target[0].hypot(target[1]).min(a[0].hypot(a[1]));
        if len2 == 0.0 {
            return r_end;
        }
        let t = -(a[0] * ab[0] + a[1] * ab[1]) / len2;
        if !(t > 0.0 && t < 1.0) {
            return r_end;
        }
        let d = (a[0] * ab[1] - a[1] * ab[0]).abs() / len2.sqrt();
        if d <= self.options.center_radius_m {
            0.0
        } else {
            d
        }
    }

    fn rest_points(&self, duration: f64) -> Vec<TrajPoint> {
        let p = TrajPoint {
            t: 0.0,
            q: self.q_end,
            ..TrajPoint::default()
        };
        vec![p, TrajPoint { t: duration, ..p }]
    }

    /// A time-optimal turn of the bed by `delta` at rest elsewhere (trapezoid in θ).
    fn rotation_points(&self, delta: f64) -> Vec<TrajPoint> {
        let limits = &self.options.joints[0];
        let (w, a) = (
            limits.velocity,
            limits.acceleration * self.options.acceleration_safety,
        );
        let dist = delta.abs();
        let sign = delta.signum();
        let q0 = self.q_end;
        let at = |t: f64, theta: f64, w: f64, acc: f64| TrajPoint {
            t,
            q: [q0[0] + sign * theta, q0[1], q0[2]],
            qd: [sign * w, 0.0, 0.0],
            qdd: [sign * acc, 0.0, 0.0],
            tool_speed: q0[1].abs() * w,
        };
        let t_acc = w / a;
        if a * t_acc * t_acc >= dist {
            let t1 = (dist / a).sqrt();
            vec![
                at(0.0, 0.0, 0.0, a),
                at(t1, 0.5 * dist, a * t1, -a),
                at(2.0 * t1, dist, 0.0, -a),
            ]
        } else {
            let d_acc = 0.5 * a * t_acc * t_acc;
            let t_cruise = (dist - 2.0 * d_acc) / w;
            vec![
                at(0.0, 0.0, 0.0, a),
                at(t_acc, d_acc, w, 0.0),
                at(t_acc + t_cruise, dist - d_acc, w, -a),
                at(2.0 * t_acc + t_cruise, dist, 0.0, -a),
            ]
        }
    }

    fn push_fixed(
        &mut self,
        seq: u64,
        points: Vec<TrajPoint>,
        last: bool,
        out: &mut Vec<PlannedMove>,
    ) {
        // Everything before must come to rest: plan and emit it, then the fixed block.
        self.flush(out);
        if let Some(p) = points.last() {
            self.q_end = p.q;
        }
        self.queue_block(Block {
            kind: BlockKind::Fixed { points },
            sequence: seq,
            last_of_move: last,
        });
        self.flush(out);
    }

    /// Queue a block; after a move's last one, note where the move leaves the joints.
    fn queue_block(&mut self, block: Block) {
        if block.last_of_move {
            self.move_ends.push_back(MoveEnd {
                sequence: block.sequence,
                q: self.q_end,
                p_m: self.p_end,
                previous_extruding: self.previous_extruding,
            });
        }
        self.queue.push_back(block);
    }

    fn push_block(&mut self, block: Block, out: &mut Vec<PlannedMove>) {
        if matches!(block.kind, BlockKind::Path { .. }) {
            self.path_blocks_queued += 1;
        }
        self.queue_block(block);
        if self.path_blocks_queued >= self.options.lookahead_blocks {
            // Emit the first three quarters; the rest stays to be joined smoothly with what
            // follows (and keeps the stop at the end of the queue reachable).
            let emit_paths = (self.options.lookahead_blocks * 3 / 4).max(1);
            let mut paths = 0;
            let mut count = 0;
            for b in &self.queue {
                count += 1;
                if matches!(b.kind, BlockKind::Path { .. }) {
                    paths += 1;
                    if paths >= emit_paths {
                        break;
                    }
                }
            }
            self.emit(count, out);
        }
    }

    fn push_line(&mut self, seq: u64, target: [f64; 3], feed: f64, out: &mut Vec<PlannedMove>) {
        let a = self.p_end;
        let ab = [target[0] - a[0], target[1] - a[1], target[2] - a[2]];
        let xy_len2 = ab[0] * ab[0] + ab[1] * ab[1];
        let r_a = self.q_end[1];
        let at_centre = a[0].hypot(a[1]) <= 1e-12;
        if xy_len2 == 0.0 {
            // z only.
            self.push_path(
                seq,
                target,
                feed,
                true,
                self.q_end[1].signum_or_one(),
                true,
                out,
            );
            return;
        }
        // Distance from the centre to the line's support, and where the closest point lies.
        let cross = a[0] * ab[1] - a[1] * ab[0];
        let d = cross.abs() / xy_len2.sqrt();
        let t_closest = -(a[0] * ab[0] + a[1] * ab[1]) / xy_len2;
        // A line the radial test below would take for one through the centre is through it,
        // whatever the centre zone (with none, rounding leaves such a line 1e-19 m off).
        let radial = d <= 1e-15 * (1.0 + xy_len2.sqrt());
        let through = radial || d <= self.options.center_radius_m;
        if at_centre {
            // Leaving the centre: point the arm at the target first (θ is free at r = 0).
            let reference = self.q_end[0];
            let (theta, sign) = self.heading_from_centre(target, reference);
            let delta = theta - reference;
            if delta != 0.0 {
                let rotation = self.rotation_points(delta);
                self.push_fixed(seq, rotation, false, out);
            }
            self.q_end[0] = theta;
            self.q_end[1] = 0.0;
            self.push_path(seq, target, feed, true, sign, true, out);
            return;
        }
        if through && t_closest > 0.0 && t_closest < 1.0 {
            // Through the centre: in to the centre (radial), then out.
            let centre = [0.0, 0.0, a[2] + ab[2] * t_closest];
            let sign_in = r_a.signum_or_one();
            self.push_path(seq, centre, feed, true, sign_in, false, out);
            if self.options.allow_negative_r {
                // Cross with θ held, up to the residual angle of a near miss (turned at rest).
                let theta_out = continuous_theta(target[0], target[1], self.q_end[0], -sign_in);
                let delta = theta_out - self.q_end[0];
                if delta.abs() > 1e-12 {
                    let rotation = self.rotation_points(delta);
                    self.push_fixed(seq, rotation, false, out);
                    self.q_end[0] = theta_out;
                }
                self.push_path(seq, target, feed, true, -sign_in, true, out);
            } else {
                let theta_out = continuous_theta(
                    target[0],
                    target[1],
                    self.q_end[0] + std::f64::consts::PI,
                    1.0,
                );
                let rotation = self.rotation_points(theta_out - self.q_end[0]);
                self.push_fixed(seq, rotation, false, out);
                self.q_end[0] = theta_out;
                self.push_path(seq, target, feed, true, 1.0, true, out);
            }
            return;
        }
        let sign = r_a.signum_or_one();
        self.push_path(seq, target, feed, radial, sign, true, out);
    }

    /// θ and the sign of r for leaving the centre towards `target`, nearest to `reference`.
    fn heading_from_centre(&self, target: [f64; 3], reference: f64) -> (f64, f64) {
        let positive = continuous_theta(target[0], target[1], reference, 1.0);
        if !self.options.allow_negative_r {
            return (positive, 1.0);
        }
        let negative = continuous_theta(target[0], target[1], reference, -1.0);
        if (negative - reference).abs() < (positive - reference).abs() {
            (negative, -1.0)
        } else {
            (positive, 1.0)
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn push_path(
        &mut self,
        seq: u64,
        target: [f64; 3],
        feed: f64,
        radial: bool,
        sign: f64,
        last: bool,
        out: &mut Vec<PlannedMove>,
    ) {
        let a = self.p_end;
        let mut q_a = self.q_end;
        if !radial {
            // Continuity: θ of the actual start point nearest to the current θ.
            q_a[0] = continuous_theta(sign * a[0], sign * a[1], q_a[0], 1.0);
        }
        let line = Line {
            a,
            b: target,
            q_a,
            sign,
            radial,
        };
        let length = line.length();
        let spacing = self.options.max_node_spacing_m.min(length / 2.0);
        subdivide(
            &line,
            self.options.path_tolerance_m,
            spacing,
            &mut self.scratch_s,
        );
        let nodes: Vec<PathNode> = self.scratch_s.iter().map(|&s| line.node(s)).collect();
        let mut q_b = nodes.last().map_or(q_a, |n| n.q);
        if radial && target[0].hypot(target[1]) <= 1e-12 {
            q_b[1] = 0.0; // land exactly on the centre
        }
        let theta_rate_peak = (!radial).then(|| {
            let u = [(target[0] - a[0]) / length, (target[1] - a[1]) / length];
            let uu = u[0] * u[0] + u[1] * u[1];
            let s_star = -(a[0] * u[0] + a[1] * u[1]) / uu;
            let closest = [a[0] + u[0] * s_star, a[1] + u[1] * s_star];
            let c = a[0] * u[1] - a[1] * u[0];
            (
                s_star,
                c.abs() / (closest[0] * closest[0] + closest[1] * closest[1]),
            )
        });
        self.q_end = q_b;
        self.p_end = target;
        self.push_block(
            Block {
                kind: BlockKind::Path {
                    feed,
                    nodes,
                    theta_rate_peak,
                },
                sequence: seq,
                last_of_move: last,
            },
            out,
        );
    }

    /// Plan the first `count` blocks (with the whole queue as lookahead) and emit them.
    fn emit(&mut self, count: usize, out: &mut Vec<PlannedMove>) {
        if count == 0 {
            return;
        }
        // Speed nodes of the leading run of path blocks (up to the first non-path block).
        let run_end = self
            .queue
            .iter()
            .position(|b| !matches!(b.kind, BlockKind::Path { .. } | BlockKind::Marker))
            .unwrap_or(self.queue.len());
        self.scratch_nodes.clear();
        let mut previous_dq: Option<Joints> = None;
        for block in self.queue.iter().take(run_end) {
            let BlockKind::Path {
                nodes,
                feed,
                theta_rate_peak,
            } = &block.kind
            else {
                continue;
            };
            for (k, n) in nodes.iter().enumerate() {
                // Joint rates per unit path length bound over both adjacent pieces: v² is
                // linear and q' monotonic between nodes, so q'·v then stays within the limit
                // inside the pieces too.
                let mut envelope = n.dq.map(f64::abs);
                for m in [k.checked_sub(1).map(|i| &nodes[i]), nodes.get(k + 1)]
                    .into_iter()
                    .flatten()
                {
                    for j in 0..3 {
                        envelope[j] = envelope[j].max(m.dq[j].abs());
                    }
                }
                let mut vmax2 = self.limits.vmax2(&envelope, &n.ddq, *feed);
                if let Some((s_star, rate)) = *theta_rate_peak {
                    let before = if k > 0 { nodes[k - 1].s } else { n.s };
                    let after = nodes.get(k + 1).map_or(n.s, |m| m.s);
                    if before <= s_star && s_star <= after && rate > 0.0 {
                        vmax2 = vmax2.min((self.limits.joint_velocity[0] / rate).powi(2));
                    }
                }
                let ds = if k == 0 { 0.0 } else { n.s - nodes[k - 1].s };
                if k == 0 {
                    if let Some(dq_in) = previous_dq {
                        // Corner: every joint's velocity jump within its limit.
                        for j in 0..3 {
                            let jump = (n.dq[j] - dq_in[j]).abs();
                            if jump > 1e-15 {
                                vmax2 = vmax2
                                    .min((self.options.joints[j].velocity_jump / jump).powi(2));
                            }
                        }
                        if let Some(last) = self.scratch_nodes.last_mut() {
                            last.vmax2 = last.vmax2.min(vmax2);
                        }
                    }
                }
                self.scratch_nodes.push(SpeedNode {
                    ds,
                    dq: n.dq,
                    ddq: n.ddq,
                    vmax2,
                });
            }
            previous_dq = nodes.last().map(|n| n.dq);
        }
        let mut v2 = std::mem::take(&mut self.scratch_v2);
        plan_speeds(&self.scratch_nodes, self.v2_head, &self.limits, &mut v2);
        // Walk the blocks to emit, turning node speeds into timed points.
        let mut node_index = 0;
        for _ in 0..count {
            let Some(block) = self.queue.pop_front() else {
                break;
            };
            let move_index = self
                .moves
                .iter()
                .position(|m| m.sequence == block.sequence)
                .expect("every queued block has its move");
            let mut points = Vec::new();
            match &block.kind {
                BlockKind::Path { nodes, .. } => {
                    self.path_blocks_queued -= 1;
                    let mut t = self.t_head;
                    for (k, n) in nodes.iter().enumerate() {
                        let i = node_index + k;
                        let v = v2[i].max(0.0).sqrt();
                        if k > 0 {
                            let v_prev = v2[i - 1].max(0.0).sqrt();
                            let ds = n.s - nodes[k - 1].s;
                            if v + v_prev > 0.0 {
                                t += 2.0 * ds / (v + v_prev);
                            }
                        }
                        // Acceleration of the piece leaving the node (entering, at the end).
                        let a = if k + 1 < nodes.len() {
                            (v2[i + 1] - v2[i]) / (2.0 * (nodes[k + 1].s - n.s))
                        } else if k > 0 {
                            (v2[i] - v2[i - 1]) / (2.0 * (n.s - nodes[k - 1].s))
                        } else {
                            0.0
                        };
                        let v_sq = v * v;
                        points.push(TrajPoint {
                            t,
                            q: n.q,
                            qd: [n.dq[0] * v, n.dq[1] * v, n.dq[2] * v],
                            qdd: [
                                n.ddq[0] * v_sq + n.dq[0] * a,
                                n.ddq[1] * v_sq + n.dq[1] * a,
                                n.ddq[2] * v_sq + n.dq[2] * a,
                            ],
                            tool_speed: v,
                        });
                    }
                    node_index += nodes.len();
                    self.t_head = t;
                    self.v2_head = v2.get(node_index - 1).copied().unwrap_or(0.0);
                }
                BlockKind::Fixed { points: fixed } => {
                    for p in fixed {
                        points.push(TrajPoint {
                            t: self.t_head + p.t,
                            ..*p
                        });
                    }
                    self.t_head = points.last().map_or(self.t_head, |p| p.t);
                    self.v2_head = 0.0;
                }
                BlockKind::Marker => {
                    points.push(TrajPoint {
                        t: self.t_head,
                        ..self.last_emitted
                    });
                }
            }
            if let Some(p) = points.last() {
                self.last_emitted = *p;
            }
            self.moves[move_index].points.extend(points);
            if block.last_of_move {
                let end = self
                    .move_ends
                    .pop_front()
                    .filter(|e| e.sequence == block.sequence)
                    .expect("a move's last block has its end noted");
                self.moves[move_index].resume = ResumePoint {
                    t_s: self.t_head,
                    // Nothing queued behind: the plan ends at rest (as below).
                    path_speed2: if self.queue.is_empty() && node_index > 0 {
                        0.0
                    } else {
                        self.v2_head
                    },
                    q: end.q,
                    p_m: end.p_m,
                    last_point: self.last_emitted,
                    previous_extruding: end.previous_extruding,
                };
                // Moves complete in order (blocks are queued in move order).
                while let Some(front) = self.moves.front() {
                    if front.sequence > block.sequence {
                        break;
                    }
                    out.push(self.moves.pop_front().expect("front exists"));
                }
            }
        }
        // What remains was planned against this lookahead; the speeds of the first remaining
        // node are fixed by what was emitted.
        if node_index > 0 && self.queue.is_empty() {
            self.v2_head = 0.0;
        }
        self.scratch_v2 = v2;
    }
}

/// A joint's position limits as the planner keeps to them (none: unbounded); with negative
/// radii allowed, the arm's is symmetric about the centre.
pub(crate) fn position_range(options: &PlannerOptions, joint: usize) -> (f64, f64) {
    let (min, max) = options.joints[joint]
        .position
        .unwrap_or((f64::NEG_INFINITY, f64::INFINITY));
    if joint == 1 && options.allow_negative_r {
        (-max, max)
    } else {
        (min, max)
    }
}

/// Where a plan starts: the initial joints, a rounding past a limit taken back onto it (a
/// radius of -5 µm would otherwise set the sign of every radius after it).
fn start_joints(options: &PlannerOptions) -> Joints {
    std::array::from_fn(|j| {
        let (min, max) = position_range(options, j);
        options.initial_joints[j].max(min).min(max)
    })
}

trait SignumOrOne {
    fn signum_or_one(self) -> f64;
}

impl SignumOrOne for f64 {
    /// The sign of a radius, taking 0 as positive.
    fn signum_or_one(self) -> f64 {
        if self < 0.0 {
            -1.0
        } else {
            1.0
        }
    }
}
