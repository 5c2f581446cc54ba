//! Telling a restarted producer's repeats from new messages, on links whose messages follow an
//! order of their own (a move's step segments by move sequence, trajectories by their times).
//!
//! A producer acknowledges its input only after publishing what it made of it, so a producer
//! killed after publishing and before its acknowledgement got through is sent that input again
//! when it restarts, and publishes the same messages again (the planner does so bit for bit:
//! `polar_planner::resume`). No acknowledgement can close that window — the publication and the
//! acknowledgement are two messages, and the process can die between them — so every consumer
//! drops the repeats itself, with [`ReplayFilter`].
//!
//! Each message has a key that never decreases along the stream. A message with a key below
//! the highest seen is a repeat. Several messages may share a key (the segments of one move,
//! zero-time moves at one instant): of those, a new writer's first ones are repeats as long as
//! it has not sent more of that key than were seen. This needs the repeated stretch to start
//! at a key no message before it shares, which is why the planner acknowledges only after a
//! move that takes time. A stream numbered by its producer across restarts (the screw
//! driver's commands) needs no key: [`SequenceJoin`] drops repeats by number.

/// What to do with a message ([`ReplayFilter::admit`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Admit {
    New,
    /// Seen before: from a restarted producer going over what it had already sent.
    Repeat,
}

/// The keys seen on one link and the writer sending it now. `W` identifies a writer (a DDS
/// publisher GID).
#[derive(Clone, Debug)]
pub struct ReplayFilter<K, W> {
    highest: Option<K>,
    /// Messages seen with key `highest`.
    at_highest: u64,
    writer: Option<W>,
    /// Messages the current writer sent with key `highest`.
    from_writer_at_highest: u64,
    repeats: u64,
}

impl<K, W> Default for ReplayFilter<K, W> {
    fn default() -> Self {
        ReplayFilter {
            highest: None,
            at_highest: 0,
            writer: None,
            from_writer_at_highest: 0,
            repeats: 0,
        }
    }
}

impl<K: Ord, W: PartialEq> ReplayFilter<K, W> {
    pub fn new() -> Self {
        Self::default()
    }

    /// Judge the next message from `writer` with `key`.
    pub fn admit(&mut self, key: K, writer: W) -> Admit {
        if self.writer.as_ref() != Some(&writer) {
            self.writer = Some(writer);
            self.from_writer_at_highest = 0;
        }
        let verdict = match self.highest.as_ref().map(|h| key.cmp(h)) {
            None | Some(std::cmp::Ordering::Greater) => {
                self.highest = Some(key);
                self.at_highest = 1;
                self.from_writer_at_highest = 1;
                Admit::New
            }
            Some(std::cmp::Ordering::Less) => Admit::Repeat,
            Some(std::cmp::Ordering::Equal) => {
                self.from_writer_at_highest += 1;
                if self.from_writer_at_highest <= self.at_highest {
                    Admit::Repeat
                } else {
                    self.at_highest += 1;
                    Admit::New
                }
            }
        };
        if verdict == Admit::Repeat {
            self.repeats += 1;
        }
        verdict
    }

    /// Messages dropped as repeats so far.
    pub fn repeats(&self) -> u64 {
        self.repeats
    }
}

/// How far a message's stamp may be from where the one before it ended (ns): the same plan
/// time, rounded to a nanosecond separately; anything lost leaves a gap of its length.
pub const TIMELINE_TOLERANCE_NS: i64 = 1_000;

/// What became of a step segment ([`StepsJoin::take`]).
#[derive(Clone, Debug, PartialEq)]
pub enum Joined {
    /// Continues the plan: execute it.
    New,
    /// A restarted planner's repeat of a segment already taken: drop it.
    Repeat,
    /// It does not start where the plan taken so far ends: something before it was lost.
    Gap {
        move_sequence: u64,
        /// Where the plan taken so far ends, and where this segment's move starts (ns).
        expected_ns: i64,
        found_ns: i64,
    },
}

/// A machine's intake of `/polar/steps`: a restarted planner's repeats dropped (keyed by move
/// sequence: a move's segments share it), and every segment checked to continue the plan —
/// a move starts where the move before it ended — so a lost segment is found, not stepped over.
#[derive(Clone, Debug)]
pub struct StepsJoin<W> {
    replay: ReplayFilter<u64, W>,
    /// The move of the last segment taken: its sequence, start stamp, and the plan time of
    /// its segments taken so far.
    last: Option<(u64, i64, f64)>,
    first_start_ns: Option<i64>,
}

impl<W> Default for StepsJoin<W> {
    fn default() -> Self {
        StepsJoin {
            replay: ReplayFilter::default(),
            last: None,
            first_start_ns: None,
        }
    }
}

impl<W: PartialEq> StepsJoin<W> {
    pub fn new() -> Self {
        Self::default()
    }

    /// Judge the next segment, from `writer`.
    pub fn take(&mut self, segment: &polar_cell_msgs::StepSegment, writer: W) -> Joined {
        if self.replay.admit(segment.move_sequence, writer) == Admit::Repeat {
            return Joined::Repeat;
        }
        let start_ns = segment.header.stamp.as_nanos();
        match self.last {
            Some((sequence, move_start_ns, taken_s)) if sequence != segment.move_sequence => {
                let expected_ns = move_end_ns(move_start_ns, taken_s);
                if (start_ns - expected_ns).abs() > TIMELINE_TOLERANCE_NS {
                    return Joined::Gap {
                        move_sequence: segment.move_sequence,
                        expected_ns,
                        found_ns: start_ns,
                    };
                }
                self.last = Some((segment.move_sequence, start_ns, segment.duration_s));
            }
            Some((_, _, ref mut taken_s)) => *taken_s += segment.duration_s,
            None => {
                self.last = Some((segment.move_sequence, start_ns, segment.duration_s));
                self.first_start_ns = Some(start_ns);
            }
        }
        Joined::New
    }

    /// Segments dropped as repeats so far.
    pub fn repeats(&self) -> u64 {
        self.replay.repeats()
    }

    /// Stamp of the first segment taken (the plan's start, unless its first segments were
    /// lost).
    pub fn first_start_ns(&self) -> Option<i64> {
        self.first_start_ns
    }

    /// Stamp of the end of the plan taken so far.
    pub fn end_ns(&self) -> Option<i64> {
        self.last
            .map(|(_, move_start_ns, taken_s)| move_end_ns(move_start_ns, taken_s))
    }
}

/// Stamp where a move that started at `move_start_ns` ends after `taken_s` of its segments.
fn move_end_ns(move_start_ns: i64, taken_s: f64) -> i64 {
    move_start_ns + (taken_s * 1e9).round() as i64
}

/// What became of a numbered message ([`SequenceJoin::take`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Numbered {
    /// The next one: take it.
    New,
    /// Taken before (a restarted producer sends again what followed its last
    /// acknowledgement, with the same numbers): drop it.
    Repeat,
    /// Messages between the last taken and this one were lost.
    Gap { expected: u64, found: u64 },
}

/// A consumer's intake of a stream its producer numbers 0, 1, 2, … across restarts
/// (`/screw/command`): repeats are dropped by number, and a lost message is found.
#[derive(Clone, Debug, Default)]
pub struct SequenceJoin {
    next: u64,
    repeats: u64,
}

impl SequenceJoin {
    pub fn new() -> Self {
        Self::default()
    }

    /// Judge the next message, numbered `sequence`.
    pub fn take(&mut self, sequence: u64) -> Numbered {
        if sequence < self.next {
            self.repeats += 1;
            Numbered::Repeat
        } else if sequence > self.next {
            Numbered::Gap {
                expected: self.next,
                found: sequence,
            }
        } else {
            self.next += 1;
            Numbered::New
        }
    }

    /// The number of the next message to take.
    pub fn next(&self) -> u64 {
        self.next
    }

    /// Messages dropped as repeats so far.
    pub fn repeats(&self) -> u64 {
        self.repeats
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn feed(filter: &mut ReplayFilter<u64, u8>, writer: u8, keys: &[u64]) -> Vec<u64> {
        keys.iter()
            .copied()
            .filter(|&k| filter.admit(k, writer) == Admit::New)
            .collect()
    }

    #[test]
    fn numbered_repeats_are_dropped_and_gaps_found() {
        let mut join = SequenceJoin::new();
        let taken: Vec<Numbered> = [0, 1, 2, 1, 2, 3].iter().map(|&k| join.take(k)).collect();
        use Numbered::*;
        assert_eq!(taken, [New, New, New, Repeat, Repeat, New]);
        assert_eq!(join.repeats(), 2);
        assert_eq!(
            join.take(6),
            Gap {
                expected: 4,
                found: 6
            }
        );
        // A gap takes nothing: the stream is still waiting for 4.
        assert_eq!(join.next(), 4);
        assert_eq!(join.take(4), New);
    }

    #[test]
    fn one_writer_passes_everything_including_equal_keys() {
        let mut f = ReplayFilter::new();
        assert_eq!(
            feed(&mut f, 1, &[0, 0, 1, 1, 1, 2, 5]),
            vec![0, 0, 1, 1, 1, 2, 5]
        );
        assert_eq!(f.repeats(), 0);
    }

    /// Moves 3 and 4 had 3 and 2 segments; the first writer died two segments into move 4's
    /// (one lost); the restarted one sends again from move 3.
    #[test]
    fn a_restarted_writer_repeats_are_dropped_and_its_new_messages_kept() {
        let mut f = ReplayFilter::new();
        assert_eq!(feed(&mut f, 1, &[2, 3, 3, 3, 4]), vec![2, 3, 3, 3, 4]);
        assert_eq!(feed(&mut f, 2, &[3, 3, 3, 4, 4, 5, 5]), vec![4, 5, 5]);
        assert_eq!(f.repeats(), 4);
        // And once more, after nothing new had been sent.
        assert_eq!(feed(&mut f, 3, &[5, 5, 6]), vec![6]);
    }

    proptest! {
        /// Whatever the stream and wherever a writer dies and its successor resumes (at a key
        /// nothing before it shares, and no later than what it had sent), what comes through is
        /// the stream once, in order.
        #[test]
        fn restarts_anywhere_deliver_the_stream_once(
            runs in proptest::collection::vec(1u64..4, 1..30),
            cuts in proptest::collection::vec((0usize..100, 0usize..100), 0..4),
        ) {
            // The stream: key k repeated runs[k] times.
            let stream: Vec<u64> = runs
                .iter()
                .enumerate()
                .flat_map(|(k, &n)| std::iter::repeat_n(k as u64, n as usize))
                .collect();
            let starts: Vec<usize> = (0..stream.len())
                .filter(|&i| i == 0 || stream[i] != stream[i - 1])
                .collect();
            let mut f = ReplayFilter::new();
            let mut out = Vec::new();
            let mut at = 0usize; // next index the current writer sends
            let mut resume = 0usize; // where the current writer started (its resume point)
            let mut writer = 0u8;
            for (sent, back) in cuts {
                // It sends some, dies, and the next one resumes at a key start between its
                // own resume point and what it sent.
                let until = (at + sent % (stream.len() - at + 1)).min(stream.len());
                out.extend(stream[at..until].iter().copied().filter(|&k| f.admit(k, writer) == Admit::New));
                let candidates: Vec<usize> =
                    starts.iter().copied().filter(|&s| s >= resume && s <= until).collect();
                if candidates.is_empty() {
                    at = until;
                    continue;
                }
                resume = candidates[back % candidates.len()];
                at = resume;
                writer += 1;
            }
            out.extend(stream[at..].iter().copied().filter(|&k| f.admit(k, writer) == Admit::New));
            prop_assert_eq!(out, stream);
        }
    }

    fn segment(move_sequence: u64, start_s: f64, duration_s: f64) -> polar_cell_msgs::StepSegment {
        polar_cell_msgs::StepSegment {
            header: polar_cell_msgs::Header {
                stamp: polar_cell_msgs::Time::after(1_000_000_000, start_s),
                frame_id: String::new(),
            },
            move_sequence,
            duration_s,
            ..Default::default()
        }
    }

    /// Move 1 (two segments, 0.3 s), move 2 (one, 0.1 s); the planner dies after move 2's
    /// first... and resumes at move 2: its repeat is dropped, move 3 continues at 0.4 s.
    #[test]
    fn a_resumed_plan_joins_and_a_lost_segment_is_a_gap() {
        let mut join = StepsJoin::new();
        assert_eq!((join.first_start_ns(), join.end_ns()), (None, None));
        assert_eq!(join.take(&segment(1, 0.0, 0.1), 'a'), Joined::New);
        assert_eq!(join.take(&segment(1, 0.0, 0.2), 'a'), Joined::New);
        assert_eq!(join.end_ns(), Some(1_300_000_000));
        assert_eq!(join.take(&segment(2, 0.3, 0.1), 'a'), Joined::New);
        assert_eq!(join.take(&segment(2, 0.3, 0.1), 'b'), Joined::Repeat);
        assert_eq!(join.take(&segment(3, 0.4, 0.5), 'b'), Joined::New);
        assert_eq!(join.repeats(), 1);
        assert_eq!(join.first_start_ns(), Some(1_000_000_000));
        assert_eq!(join.end_ns(), Some(1_900_000_000));
        // Move 4's second segment is lost; move 5 starts where move 4 would have ended.
        assert_eq!(join.take(&segment(4, 0.9, 0.25), 'b'), Joined::New);
        assert_eq!(
            join.take(&segment(5, 1.4, 0.1), 'b'),
            Joined::Gap {
                move_sequence: 5,
                expected_ns: 2_150_000_000,
                found_ns: 2_400_000_000
            }
        );
    }
}
