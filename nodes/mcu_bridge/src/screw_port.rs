//! A machine whose screw is on an ASCII serial line: any [`Machine`] for the steppers, a
//! [`ScrewLine`] for the screw's servo amplifier.
//!
//! [`WithScrewLine`] takes the screw commands away from the machine it wraps (the MCU then
//! drives steppers only) and sends them as lines at the machine's plan time, scaled with its
//! feed scale and with the pin closed while held at rest or stopped. What it publishes for the
//! screw joint is what the amplifier was told, integrated over time. Faults, emergency stops,
//! a dropped plan and the end of the node all send "rpm 0, pin closed" at once.

use cell_machine::{Machine, MachineState, PlayerState};
use polar_cell_msgs::{ScrewCommand, StepSegment};

use crate::screw_line::{LineClock, LineCounters, ScrewLine, ScrewLineError};

/// Where the lines go.
pub trait LinePort {
    type Error: std::fmt::Display;
    /// Send `text` at machine time `now_ns`.
    fn send(&mut self, now_ns: i64, text: &str) -> Result<(), Self::Error>;
}

/// What goes wrong with the machine or its screw line.
#[derive(Debug, thiserror::Error)]
pub enum WithScrewLineError<E: std::fmt::Display> {
    #[error(transparent)]
    Machine(E),
    #[error(transparent)]
    Line(#[from] ScrewLineError),
    #[error("the screw's serial line: {0}")]
    Port(String),
    #[error(
        "{count} screw commands arrived before any step segment: more than can be held ({capacity})"
    )]
    TooManyEarly { count: usize, capacity: usize },
}

/// `M` for the steppers, the screw on `P`.
pub struct WithScrewLine<M: Machine, P: LinePort> {
    inner: M,
    line: ScrewLine,
    port: P,
    capacity: usize,
    early: Vec<ScrewCommand>,
    /// The plan the line's commands belong to (its epoch): a new one starts the line afresh.
    epoch_ns: Option<i64>,
    last_tick_ns: Option<i64>,
    angle_rad: f64,
    port_error: Option<String>,
    /// A failed line's stop is tried again no sooner than this (machine ns): once a period,
    /// not every tick (a blocked write waits, and the loop with it).
    retry_at_ns: i64,
    input_finished: bool,
}

impl<M: Machine, P: LinePort> WithScrewLine<M, P> {
    /// `capacity`: screw commands held at most (as the machine's own queue would).
    pub fn new(inner: M, line: ScrewLine, port: P, capacity: usize) -> WithScrewLine<M, P> {
        WithScrewLine {
            inner,
            line,
            port,
            capacity,
            early: Vec::new(),
            epoch_ns: None,
            last_tick_ns: None,
            angle_rad: 0.0,
            port_error: None,
            retry_at_ns: i64::MIN,
            input_finished: false,
        }
    }

    pub fn inner(&self) -> &M {
        &self.inner
    }

    pub fn port(&self) -> &P {
        &self.port
    }

    pub fn port_mut(&mut self) -> &mut P {
        &mut self.port
    }

    pub fn counters(&self) -> LineCounters {
        self.line.counters()
    }

    fn push(&mut self, msg: &ScrewCommand, epoch_ns: i64) -> Result<(), ScrewLineError> {
        let plan_s = (msg.header.stamp.as_nanos() - epoch_ns) as f64 * 1e-9;
        self.line
            .push(plan_s.max(0.0), msg.rpm, msg.pin_open, msg.source_line)
    }

    fn send(&mut self, now_ns: i64, text: Option<String>) -> Result<(), String> {
        let Some(text) = text else {
            return Ok(());
        };
        let sent = self.port.send(now_ns, &text).map_err(|e| e.to_string());
        if let Err(e) = &sent {
            // Whatever part of the line went out, the amplifier's state is unknown now: the
            // next stop is sent again (every period while it fails, and at a reset).
            self.line.forget_sent();
            self.retry_at_ns = now_ns + (self.line.min_period_s() * 1e9) as i64;
            // The screw is out of reach: the steppers stop too, at once.
            if self.port_error.is_none() {
                self.port_error = Some(e.clone());
                self.inner.emergency_stop();
            }
        }
        sent
    }

    /// The screw stops now (whatever the rate limit), and what was queued for it goes.
    fn stop_screw(&mut self, now_ns: i64) -> Result<(), String> {
        self.early.clear();
        self.epoch_ns = None;
        self.input_finished = false;
        let stop = self.line.stop_now(now_ns as f64 * 1e-9);
        self.send(now_ns, stop)
    }

    fn now_ns(&self) -> i64 {
        self.last_tick_ns.unwrap_or(0)
    }

    /// Tell the amplifier "rpm 0, pin closed" before anything else: one left turning by an
    /// earlier session that ended badly stops now, and a line that cannot be written is
    /// found before the print starts.
    pub fn start_stopped(&mut self) -> Result<(), WithScrewLineError<M::Error>> {
        self.line.forget_sent();
        self.stop_screw(self.now_ns())
            .map_err(WithScrewLineError::Port)
    }
}

impl<M: Machine, P: LinePort> Machine for WithScrewLine<M, P> {
    type Error = WithScrewLineError<M::Error>;

    fn on_segment(&mut self, msg: &StepSegment) -> Result<(), Self::Error> {
        self.inner
            .on_segment(msg)
            .map_err(WithScrewLineError::Machine)?;
        if let (None, Some(epoch)) = (self.epoch_ns, self.inner.epoch_ns()) {
            self.epoch_ns = Some(epoch);
            for early in std::mem::take(&mut self.early) {
                self.push(&early, epoch)?;
            }
        }
        Ok(())
    }

    fn on_screw(&mut self, msg: &ScrewCommand) -> Result<(), Self::Error> {
        match self.epoch_ns {
            Some(epoch) => Ok(self.push(msg, epoch)?),
            None if self.early.len() < self.capacity => {
                self.early.push(msg.clone());
                Ok(())
            }
            None => Err(WithScrewLineError::TooManyEarly {
                count: self.early.len() + 1,
                capacity: self.capacity,
            }),
        }
    }

    fn free_slots(&self) -> (usize, usize) {
        let (segments, screw) = self.inner.free_slots();
        // No room for the screw where the machine takes nothing (not ready, stopped).
        let room = self
            .capacity
            .saturating_sub(self.line.queued() + self.early.len());
        (segments, if segments == 0 && screw == 0 { 0 } else { room })
    }

    fn finish_input(&mut self) {
        self.inner.finish_input();
        self.input_finished = true;
    }

    fn on_tick(&mut self, now_ns: i64) -> Result<(), Self::Error> {
        let result = self.inner.on_tick(now_ns);
        let (rpm, _) = self.line.sent();
        if let Some(last) = self.last_tick_ns {
            self.angle_rad +=
                rpm / 60.0 * std::f64::consts::TAU * (now_ns - last).max(0) as f64 * 1e-9;
        }
        self.last_tick_ns = Some(now_ns);
        let state = self.inner.state();
        // A stopped machine, or a plan dropped (a cancel done): the screw stops with it.
        let dropped = self.epoch_ns.is_some() && self.inner.epoch_ns().is_none();
        if result.is_err() || state.state == PlayerState::Stopped || dropped {
            let reported = self.port_error.is_some();
            let stopped = if reported && now_ns < self.retry_at_ns {
                Ok(())
            } else {
                self.stop_screw(now_ns)
            };
            result.map_err(WithScrewLineError::Machine)?;
            // A line that failed is tried again every period; its error was reported once.
            return match stopped {
                Err(e) if !reported => Err(WithScrewLineError::Port(e)),
                _ => Ok(()),
            };
        }
        let running = matches!(state.state, PlayerState::Running | PlayerState::Held);
        // The plan clock stops where the plan ends; lines the rate put after that instant
        // are due all the same.
        let plan_s = if self.input_finished && self.inner.is_drained() {
            f64::INFINITY
        } else {
            state.plan_time_s
        };
        let clock = LineClock {
            machine_s: now_ns as f64 * 1e-9,
            plan_s,
            feed: if running { state.feed } else { 0.0 },
            // As the MCU (and the virtual machine): the pin stays open while a hold slows
            // (the screw at σ·rpm, so the slowed path gets its material), closes once held
            // at rest, and reopens when a resume is asked for (its delay at rest), before σ
            // ramps up.
            pin_allowed: state.state == PlayerState::Running
                || (state.state == PlayerState::Held && state.hold.is_none()),
        };
        let polled = self.line.poll(clock).map(|(text, _)| text);
        self.send(now_ns, polled).map_err(WithScrewLineError::Port)
    }

    fn state(&self) -> MachineState {
        let mut state = self.inner.state();
        let (rpm, pin_open) = self.line.sent();
        state.positions[3] = self.angle_rad;
        state.velocities[3] = rpm / 60.0 * std::f64::consts::TAU;
        state.screw_rpm = rpm;
        state.pin_open = pin_open;
        if self.port_error.is_some() {
            state.state = PlayerState::Stopped;
        }
        state
    }

    fn epoch_ns(&self) -> Option<i64> {
        self.inner.epoch_ns()
    }

    fn is_drained(&self) -> bool {
        self.inner.is_drained() && self.line.is_idle()
    }

    fn plan_ahead_s(&self) -> f64 {
        self.inner.plan_ahead_s()
    }

    fn completed(&self) -> (u64, Option<(u64, u32)>) {
        self.inner.completed()
    }

    fn underruns(&self) -> u64 {
        self.inner.underruns()
    }

    fn pause(&mut self) {
        self.inner.pause();
    }

    fn resume(&mut self) {
        self.inner.resume();
    }

    fn cancel(&mut self) {
        self.inner.cancel();
    }

    fn emergency_stop(&mut self) {
        self.inner.emergency_stop();
        let _ = self.stop_screw(self.now_ns());
    }

    fn reset(&mut self) {
        self.inner.reset();
        self.port_error = None;
        let _ = self.stop_screw(self.now_ns());
    }

    fn clock_started(&mut self, origin: std::time::Instant, speed: f64) {
        self.inner.clock_started(origin, speed);
    }

    fn diagnostics(&self) -> Vec<(&'static str, String)> {
        let mut values = self.inner.diagnostics();
        let c = self.line.counters();
        values.push(("screw_line_commands_sent", c.lines_sent.to_string()));
        values.push((
            "screw_line_worst_late_ms",
            format!("{:.1}", c.worst_late_s * 1e3),
        ));
        values.push((
            "screw_line_pin_changes_delayed",
            c.pin_changes_delayed.to_string(),
        ));
        values.push((
            "screw_line_worst_pin_delay_ms",
            format!("{:.1}", c.worst_pin_delay_s * 1e3),
        ));
        values.push((
            "screw_line_commands_overtaken",
            c.lines_overtaken.to_string(),
        ));
        if let Some(e) = &self.port_error {
            values.push(("screw_line_error", e.clone()));
        }
        values
    }
}

/// A node that goes away leaves the screw stopped and the pin closed.
impl<M: Machine, P: LinePort> Drop for WithScrewLine<M, P> {
    fn drop(&mut self) {
        let _ = self.stop_screw(self.now_ns());
    }
}
