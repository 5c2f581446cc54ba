//! Repeated log lines, at most one per sender per period.
//!
//! A node that logs every bad message it refuses hands whoever sends them a way to flood
//! `/rosout` (a participant forging 600 acknowledgements a second made the streamer log 600
//! errors a second, and a recorder keeping `/rosout`'s depth of 1 lost some). Like rclcpp's
//! `RCLCPP_ERROR_THROTTLE`, but per sender: the first is logged at once, later ones at most
//! once per period, saying how many were not logged in between.

use std::collections::HashMap;
use std::hash::Hash;
use std::time::Duration;

/// Per-key throttle of a repeated message. Times are the caller's monotonic clock.
#[derive(Debug)]
pub struct LogThrottle<K> {
    period: Duration,
    grace: Duration,
    /// Per key: when it was first seen, when it was last logged, and how many were held back
    /// since.
    keys: HashMap<K, (Duration, Option<Duration>, u64)>,
}

impl<K: Eq + Hash> LogThrottle<K> {
    /// Senders kept at most.
    pub const MAX_KEYS: usize = 1024;

    pub fn new(period: Duration) -> Self {
        Self::with_grace(period, Duration::ZERO)
    }

    /// Like [`LogThrottle::new`], but nothing of a key is logged until `grace` after its
    /// first occurrence: for what is normal for a moment (a new node's acknowledgements before
    /// its announcement has arrived) and suspect only if it lasts.
    pub fn with_grace(period: Duration, grace: Duration) -> Self {
        LogThrottle {
            period,
            grace,
            keys: HashMap::new(),
        }
    }

    /// Another occurrence for `key` at `now`: `Some(held_back)` when it is to be logged, with
    /// how many occurrences since the last logged one were not; `None` to hold it back.
    pub fn admit(&mut self, key: K, now: Duration) -> Option<u64> {
        if self.keys.len() >= Self::MAX_KEYS && !self.keys.contains_key(&key) {
            // Bounded whatever a sender does (one that makes a new writer per message): keys
            // quiet for a period past their grace go first; beyond that, new ones are not
            // logged at all.
            let quiet = self.period + self.grace;
            self.keys
                .retain(|_, (first, last, _)| now.saturating_sub(last.unwrap_or(*first)) < quiet);
            if self.keys.len() >= Self::MAX_KEYS {
                return None;
            }
        }
        let (first, last, held_back) = self.keys.entry(key).or_insert((now, None, 0));
        let due = now.saturating_sub(*first) >= self.grace
            && last.is_none_or(|last| now.saturating_sub(last) >= self.period);
        if due {
            let count = *held_back;
            (*last, *held_back) = (Some(now), 0);
            Some(count)
        } else {
            *held_back += 1;
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    #[test]
    fn the_first_of_each_key_is_logged_then_one_per_period_with_the_count_held_back() {
        let mut throttle = LogThrottle::new(ms(1000));
        assert_eq!(throttle.admit("a", ms(0)), Some(0));
        assert_eq!(
            throttle.admit("b", ms(1)),
            Some(0),
            "another sender is not held"
        );
        // 600 a second from "a": none logged until a period has passed.
        for k in 1..600 {
            assert_eq!(throttle.admit("a", ms(k * 1000 / 600)), None);
        }
        assert_eq!(throttle.admit("a", ms(1000)), Some(599));
        assert_eq!(throttle.admit("a", ms(1500)), None);
        assert_eq!(throttle.admit("a", ms(2000)), Some(1));
        // A quiet key is logged at once when it speaks again.
        assert_eq!(throttle.admit("b", ms(5000)), Some(0));
    }

    /// A sender with a new key per message grows nothing beyond MAX_KEYS: quiet keys go,
    /// and while every kept key is recent, a new one is not logged.
    #[test]
    fn the_keys_kept_are_bounded() {
        let max = LogThrottle::<u64>::MAX_KEYS as u64;
        let mut throttle = LogThrottle::new(ms(1000));
        // Within half a second: all still recent at 0.6 s.
        for k in 0..max {
            assert_eq!(throttle.admit(k, ms(k / 2)), Some(0));
        }
        assert_eq!(
            throttle.admit(max, ms(600)),
            None,
            "all kept keys are recent"
        );
        assert_eq!(throttle.keys.len() as u64, max);
        // At 1.3 s the keys last logged before 0.3 s (k ≤ 601) are quiet and make room;
        // the 422 later ones stay, with the new one.
        assert_eq!(throttle.admit(max + 1, ms(1300)), Some(0));
        assert_eq!(throttle.keys.len(), 423);
        assert!(throttle.keys.contains_key(&602) && !throttle.keys.contains_key(&601));
    }

    #[test]
    fn with_grace_nothing_is_logged_until_a_key_has_lasted() {
        let mut throttle = LogThrottle::with_grace(ms(1000), ms(2000));
        assert_eq!(throttle.admit("new node", ms(0)), None);
        assert_eq!(
            throttle.admit("new node", ms(100)),
            None,
            "its announcement is coming"
        );
        assert_eq!(throttle.admit("forger", ms(500)), None);
        assert_eq!(throttle.admit("forger", ms(2499)), None);
        assert_eq!(
            throttle.admit("forger", ms(2500)),
            Some(2),
            "it lasted: logged, with the count"
        );
        assert_eq!(throttle.admit("forger", ms(3000)), None);
        assert_eq!(throttle.admit("forger", ms(3500)), Some(1));
    }
}
