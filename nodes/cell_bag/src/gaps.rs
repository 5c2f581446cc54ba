//! Samples a recorder's reader never got, from the writers' own numbering.
//!
//! A DDS writer numbers its samples 1, 2, 3, … and a reliable reader takes them in that
//! order. A jump is samples lost on the way into the bag: evicted from a keep-last history
//! (the reader's own while the recorder lagged, or the writer's past its retention limit)
//! and declared irrelevant to the reader. Counting the jumps makes such a loss visible
//! instead of a bag that silently holds less than was published. Each writer is counted
//! from its first sample the reader took: what a volatile writer sent before the reader
//! matched was never offered to it.

use std::collections::HashMap;
use std::hash::Hash;

/// Per-writer sequence tracking for one topic. `W` identifies a writer (its GID).
#[derive(Debug)]
pub struct SequenceGaps<W> {
    last_taken: HashMap<W, i64>,
    missed: u64,
    out_of_order: u64,
}

impl<W> Default for SequenceGaps<W> {
    fn default() -> Self {
        SequenceGaps {
            last_taken: HashMap::new(),
            missed: 0,
            out_of_order: 0,
        }
    }
}

impl<W: Eq + Hash> SequenceGaps<W> {
    /// Note that the sample numbered `sequence` of `writer` was taken.
    pub fn observe(&mut self, writer: W, sequence: i64) {
        match self.last_taken.get_mut(&writer) {
            None => {
                self.last_taken.insert(writer, sequence);
            }
            Some(last) if sequence > *last => {
                self.missed += (sequence - *last - 1) as u64;
                *last = sequence;
            }
            // Reliable delivery is in order and once: a repeat or a step back is a fault of
            // the transport worth reporting, not a loss.
            Some(_) => self.out_of_order += 1,
        }
    }

    /// Samples skipped between the first and the last one taken, over all writers.
    pub fn missed(&self) -> u64 {
        self.missed
    }

    /// Samples taken again or after a later one.
    pub fn out_of_order(&self) -> u64 {
        self.out_of_order
    }

    /// Writers seen.
    pub fn writers(&self) -> usize {
        self.last_taken.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn a_writer_joined_late_is_not_a_loss_but_a_jump_after_is() {
        let mut gaps = SequenceGaps::default();
        for s in [17, 18, 19] {
            gaps.observe('a', s);
        }
        assert_eq!(gaps.missed(), 0);
        gaps.observe('a', 25);
        assert_eq!(gaps.missed(), 5, "20..=24");
    }

    #[test]
    fn writers_are_counted_apart() {
        let mut gaps = SequenceGaps::default();
        gaps.observe('a', 1);
        gaps.observe('b', 40);
        gaps.observe('a', 2);
        gaps.observe('b', 41);
        gaps.observe('a', 4);
        assert_eq!((gaps.missed(), gaps.writers()), (1, 2));
    }

    #[test]
    fn repeats_and_steps_back_are_out_of_order_not_missed() {
        let mut gaps = SequenceGaps::default();
        for s in [1, 2, 2, 1, 3] {
            gaps.observe(0u8, s);
        }
        assert_eq!((gaps.missed(), gaps.out_of_order()), (0, 2));
    }

    proptest! {
        /// Whatever subset of a writer's samples arrives (in order), the missed count is
        /// exactly the samples between the first and last taken that did not arrive.
        #[test]
        fn missed_is_what_did_not_arrive(kept in proptest::collection::vec(any::<bool>(), 1..500)) {
            let taken: Vec<i64> = (1..=kept.len() as i64).filter(|s| kept[*s as usize - 1]).collect();
            let mut gaps = SequenceGaps::default();
            for &s in &taken {
                gaps.observe((), s);
            }
            let expected = match (taken.first(), taken.last()) {
                (Some(first), Some(last)) => (last - first + 1) as u64 - taken.len() as u64,
                _ => 0,
            };
            prop_assert_eq!(gaps.missed(), expected);
            prop_assert_eq!(gaps.out_of_order(), 0);
        }
    }
}
