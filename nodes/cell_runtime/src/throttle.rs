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
    /// Per key: when it was last logged, and how many were held back since.
    keys: HashMap<K, (Duration, u64)>,
}

impl<K: Eq + Hash> LogThrottle<K> {
    pub fn new(period: Duration) -> Self {
        LogThrottle {
            period,
            keys: HashMap::new(),
        }
    }

    /// Another occurrence for `key` at `now`: `Some(held_back)` when it is to be logged, with
    /// how many occurrences since the last logged one were not; `None` to hold it back.
    pub fn admit(&mut self, key: K, now: Duration) -> Option<u64> {
        match self.keys.get_mut(&key) {
            None => {
                self.keys.insert(key, (now, 0));
                Some(0)
            }
            Some((last, held_back)) if now.saturating_sub(*last) >= self.period => {
                let count = *held_back;
                (*last, *held_back) = (now, 0);
                Some(count)
            }
            Some((_, held_back)) => {
                *held_back += 1;
                None
            }
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
}
