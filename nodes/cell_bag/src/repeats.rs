//! Leaving a restarted producer's repeats out of a bag.
//!
//! A producer killed after publishing and before its acknowledgement got through publishes the
//! same messages again when it restarts ([`cell_runtime::replay`]). The bag should hold the
//! plan once, as the machine executed it. Messages are judged by a key that never decreases
//! along their stream; a topic that carries several such streams side by side (the planner's
//! and the screw driver's `/polar/planned_joint_states`, each with its own joints and stamps)
//! is judged per *lane*, here the joint names, so one stream's stamps never hide another's.

use std::collections::HashMap;

use cell_runtime::replay::{Admit, ReplayFilter};

/// One [`ReplayFilter`] per lane of a topic. `W` identifies a writer (its GID).
#[derive(Debug)]
pub struct Repeats<W> {
    lanes: HashMap<Vec<String>, ReplayFilter<(i64, i64), W>>,
}

impl<W> Default for Repeats<W> {
    fn default() -> Self {
        Repeats {
            lanes: HashMap::new(),
        }
    }
}

impl<W: PartialEq> Repeats<W> {
    /// Judge the next message of `lane` from `writer` with `key`.
    pub fn admit(&mut self, lane: &[String], key: (i64, i64), writer: W) -> Admit {
        if let Some(filter) = self.lanes.get_mut(lane) {
            return filter.admit(key, writer);
        }
        let mut filter = ReplayFilter::new();
        let verdict = filter.admit(key, writer);
        self.lanes.insert(lane.to_vec(), filter);
        verdict
    }

    /// Messages left out as repeats so far, over all lanes.
    pub fn repeats(&self) -> u64 {
        self.lanes.values().map(ReplayFilter::repeats).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(joints: &[&str]) -> Vec<String> {
        joints.iter().map(|s| s.to_string()).collect()
    }

    /// The planner's stage joints and the screw driver's screw joint interleave on one topic
    /// with stamps of their own; the screw driver restarts (writer 3) and publishes again the
    /// samples from 0.30 s on, which it had published before its last acknowledgement.
    #[test]
    fn a_restarted_writer_repeats_are_left_out_per_lane_and_the_other_lane_is_untouched() {
        let stage = names(&["bed_theta", "arm_r", "z"]);
        let screw = names(&["screw"]);
        let mut repeats = Repeats::default();
        let ms = |t: i64| (t * 1_000_000, 0);
        let mut kept = Vec::new();
        let mut admit = |lane: &[String], t_ms: i64, writer: u8| {
            if repeats.admit(lane, ms(t_ms), writer) == Admit::New {
                kept.push((lane[0].clone(), t_ms));
            }
        };
        // The stage lane runs ahead of the screw lane (the planner is ahead).
        for t in (0..=500).step_by(20) {
            admit(&stage, t, 1);
        }
        for t in (0..=400).step_by(20) {
            admit(&screw, t, 2);
        }
        for t in (300..=600).step_by(20) {
            admit(&screw, t, 3);
        }
        for t in (520..=600).step_by(20) {
            admit(&stage, t, 1);
        }
        let times = |lane: &str| -> Vec<i64> {
            kept.iter()
                .filter(|(l, _)| l == lane)
                .map(|&(_, t)| t)
                .collect()
        };
        let every_20_ms: Vec<i64> = (0..=600).step_by(20).collect();
        assert_eq!(times("bed_theta"), every_20_ms);
        assert_eq!(times("screw"), every_20_ms);
        // 0.30 to 0.40 s: six samples the restarted driver sent again.
        assert_eq!(repeats.repeats(), 6);
    }

    /// One filter for the whole topic would drop the screw lane's samples behind the stage
    /// lane's stamps: lanes are what makes the interleaving safe.
    #[test]
    fn lanes_are_independent_of_each_others_stamps() {
        let mut repeats = Repeats::default();
        assert_eq!(repeats.admit(&names(&["a"]), (100, 0), 1), Admit::New);
        assert_eq!(repeats.admit(&names(&["b"]), (10, 0), 2), Admit::New);
        assert_eq!(repeats.admit(&names(&["b"]), (5, 0), 3), Admit::Repeat);
        assert_eq!(repeats.admit(&names(&["a"]), (50, 0), 1), Admit::Repeat);
        assert_eq!(repeats.repeats(), 2);
    }
}
