//! Plan credit from what a recorder has taken (no I/O): when no machine executes the plan (a
//! dry run), the bag is the plan's slowest consumer, so it grants the producers their
//! plan-ahead as the machine would (`/cell/plan_credit`).
//!
//! Without it a dry run's planner and screw driver plan as fast as the CPU allows and the
//! recorder, on the same two cores, falls behind their keep-last histories: a million-move
//! dry run lost 11,142 screw commands here, and 150,822 samples once the screw driver got
//! faster. With the credit, what is in flight to the bag is bounded by `horizon_s` of plan
//! time, as at machine pace.
//!
//! Each followed topic has a frontier: where the plan the recorder has taken on it ends, in
//! plan stamps (`None` until its first sample). The plan is recorded up to the lowest
//! frontier. A topic that has carried nothing yet is not waited for (a planner asked not to
//! publish steps must not stall the print), and before any topic has carried something the
//! producers get their first horizon, as from a machine that has received nothing. The
//! topics followed are the planner's (`/polar/trajectory`, `/polar/steps`): the screw
//! driver, which needs the planner's trajectories, cannot run ahead of them.

use polar_cell_msgs::Time;

/// Where the recorded plan ends and how far ahead of it producers may plan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Credit {
    /// Zero (`Time::default()`) before anything was recorded.
    pub executed_until: Time,
    /// Zero before anything was recorded: the producers' own first horizon.
    pub accept_until: Time,
}

/// The credit for the frontiers (plan stamps in ns, `None`: nothing taken yet) and horizon.
pub fn credit_for(frontiers_ns: &[Option<i64>], horizon_s: f64) -> Credit {
    match frontiers_ns.iter().flatten().min() {
        Some(&recorded_ns) => Credit {
            executed_until: Time::from_nanos(recorded_ns),
            accept_until: Time::after(recorded_ns, horizon_s),
        },
        None => Credit {
            executed_until: Time::default(),
            accept_until: Time::default(),
        },
    }
}

/// Whether a new credit should go out: the recorded plan moved by a twentieth of the horizon
/// since the last one (often enough that producers never wait on it), or `repeat_s` passed
/// (a late-joining producer learns it; a lost one is replaced).
pub fn credit_due(
    last: Option<Credit>,
    now: Credit,
    since_last_s: f64,
    horizon_s: f64,
    repeat_s: f64,
) -> bool {
    let Some(last) = last else {
        return true;
    };
    let moved_s = (now.executed_until.as_nanos() - last.executed_until.as_nanos()) as f64 * 1e-9;
    moved_s >= horizon_s / 20.0 || since_last_s >= repeat_s
}

/// Where the plan taken on one topic ends: spans that share a start stamp follow each other
/// (a move's step segments), a new start begins again. The end, not the start, is the
/// frontier: a credit from the last start would hold a planner whose last move is longer
/// than the horizon short of its own plan for good.
#[derive(Debug, Default)]
pub struct PlanEnd {
    last: Option<(i64, i64)>,
}

impl PlanEnd {
    /// The end of the plan taken so far, after a span `(start, length)`.
    pub fn after(&mut self, (start_ns, length_ns): (i64, i64)) -> i64 {
        let end_ns = match self.last {
            Some((last_start_ns, last_end_ns)) if last_start_ns == start_ns => {
                last_end_ns + length_ns
            }
            _ => start_ns + length_ns,
        };
        self.last = Some((start_ns, end_ns));
        end_ns
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_plan_ends_after_a_moves_segments_and_a_new_move_starts_again() {
        let mut end = PlanEnd::default();
        // A 3 s move in three segments (1 s, 1.5 s, 0.5 s), all stamped at its start.
        assert_eq!(end.after((10_000, 1_000)), 11_000);
        assert_eq!(end.after((10_000, 1_500)), 12_500);
        assert_eq!(end.after((10_000, 500)), 13_000);
        // The next move starts where that one ended.
        assert_eq!(end.after((13_000, 2_000)), 15_000);
        // Spans of no length at one instant, then a later one.
        let mut instants = PlanEnd::default();
        assert_eq!(instants.after((7, 0)), 7);
        assert_eq!(instants.after((7, 0)), 7);
        assert_eq!(instants.after((9, 0)), 9);
    }

    #[test]
    fn the_recorded_plan_ends_at_the_lowest_frontier_of_the_topics_that_carried_something() {
        let c = credit_for(&[Some(5_000_000_000), None, Some(3_250_000_000)], 8.0);
        assert_eq!(
            c.executed_until,
            Time {
                sec: 3,
                nanosec: 250_000_000
            }
        );
        assert_eq!(
            c.accept_until,
            Time {
                sec: 11,
                nanosec: 250_000_000
            }
        );
    }

    #[test]
    fn before_anything_is_recorded_the_producers_get_their_first_horizon() {
        // Zero times: the planner plans its own first `horizon_s` (polar_planner's
        // `credit_allows`), as from a machine that has received nothing.
        let c = credit_for(&[None, None], 8.0);
        assert_eq!(c.executed_until, Time::default());
        assert_eq!(c.accept_until, Time::default());
        assert_eq!(credit_for(&[], 8.0), c);
    }

    #[test]
    fn a_credit_goes_out_when_the_plan_moved_a_twentieth_of_the_horizon_or_to_repeat() {
        let at = |s: i64| credit_for(&[Some(s * 100_000_000)], 8.0); // tenths of a second
        assert!(credit_due(None, at(0), 0.0, 8.0, 0.1));
        // 0.3 s moved of an 8 s horizon: not yet (0.4 s is a twentieth).
        assert!(!credit_due(Some(at(10)), at(13), 0.01, 8.0, 0.1));
        assert!(credit_due(Some(at(10)), at(14), 0.01, 8.0, 0.1));
        // Unchanged, but repeated.
        assert!(!credit_due(Some(at(10)), at(10), 0.099, 8.0, 0.1));
        assert!(credit_due(Some(at(10)), at(10), 0.1, 8.0, 0.1));
    }
}
