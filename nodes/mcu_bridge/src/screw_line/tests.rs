use super::*;
use proptest::prelude::*;

fn template(t: &str) -> CommandTemplate {
    CommandTemplate::parse(t).unwrap()
}

#[test]
fn the_default_template_says_rpm_to_a_tenth_and_the_pin() {
    let t = template(DEFAULT_TEMPLATE);
    assert_eq!(t.render(123.456, true), "RPM 123.5 PIN 1\r\n");
    assert_eq!(t.render(0.04, false), "RPM 0.0 PIN 0\r\n");
    assert_eq!(t.quantum_rpm(), 0.1);
}

#[test]
fn templates_take_other_syntaxes() {
    let t = template("\\x02S{millirpm};P{pin:ON/OFF}\\x03{{{rpm}}}\\\\");
    assert_eq!(t.render(12.3456, false), "\u{2}S12346;POFF\u{3}{12.346}\\");
    assert_eq!(t.quantum_rpm(), 1e-3);
    let t = template("V{rpm:.0}\\tP{pin}\\n");
    assert_eq!(t.render(99.5, true), "V100\tP1\n");
}

#[test]
fn a_bad_template_names_what_and_where() {
    use TemplateError::*;
    let err = |t: &str| CommandTemplate::parse(t).unwrap_err();
    assert_eq!(err("RPM {rpm"), Unclosed { at: 4 });
    assert_eq!(
        err("{pin} {speed}"),
        Unknown {
            name: "speed".into(),
            at: 6
        }
    );
    assert_eq!(
        err("{pin}{rpm:.7}"),
        Unknown {
            name: "rpm:.7".into(),
            at: 5
        }
    );
    assert_eq!(
        err("{pin}{rpm}\\q"),
        BadEscape {
            escape: "q".into(),
            at: 10
        }
    );
    assert_eq!(
        err("{pin}{rpm}\\xff"),
        BadEscape {
            escape: "xff".into(),
            at: 10
        }
    );
    assert_eq!(err("{pin}{rpm}}"), LoneBrace { at: 10 });
    for words in ["pin:ON/ON", "pin:/", "pin:ON/", "pin:/OFF"] {
        assert_eq!(
            err(&format!("{{rpm}} {{{words}}}")),
            PinWords {
                name: words.into(),
                at: 6
            }
        );
    }
    assert_eq!(
        err("{rpm} {pin:AN/ÄUS}"),
        NotAscii {
            character: 'Ä',
            at: 6
        }
    );
    assert_eq!(
        err("{pin}{rpm}°"),
        NotAscii {
            character: '°',
            at: 10
        }
    );
    assert!(matches!(
        err("P{pin}"),
        Missing {
            missing: "{rpm}",
            ..
        }
    ));
    assert!(matches!(
        err("S{rpm}"),
        Missing {
            missing: "{pin}",
            ..
        }
    ));
    // The messages say it in words.
    assert_eq!(
        err("{pin} {speed}").to_string(),
        "command template: `{speed}` at byte 6 is not one of {rpm}, {rpm:.N} (N decimals, 0 \
         to 6), {millirpm}, {pin} or {pin:OPEN/CLOSED}"
    );
}

const FULL: LineClock = LineClock {
    machine_s: 0.0,
    plan_s: 0.0,
    feed: 1.0,
    pin_allowed: true,
};

/// Poll every `dt_s` of machine time (= plan time, σ = 1) up to `until_s`: the lines with
/// their times.
fn run(line: &mut ScrewLine, dt_s: f64, until_s: f64) -> Vec<(f64, String)> {
    let mut out = Vec::new();
    let per_s = (1.0 / dt_s).round();
    for k in 0..=(until_s * per_s).round() as usize {
        let t = k as f64 / per_s;
        if let Some((text, _)) = line.poll(LineClock {
            machine_s: t,
            plan_s: t,
            ..FULL
        }) {
            out.push((t, text));
        }
    }
    out
}

fn rpm_of(text: &str) -> f64 {
    text.split_whitespace().nth(1).unwrap().parse().unwrap()
}

/// Commands the screw driver already put on the rate's grid (held exact averages) pass one
/// for one, on time.
#[test]
fn commands_on_the_rate_grid_pass_one_for_one() {
    let mut line = ScrewLine::new(template("RPM {rpm} PIN {pin}"), 10.0, Hold::ZeroOrder);
    let values = [0.0, 12.5, 40.0, 40.0, 80.25, 3.0, 0.0];
    for (k, rpm) in values.iter().enumerate() {
        line.push(k as f64 / 10.0, *rpm, *rpm > 0.0, 7).unwrap();
    }
    let sent = run(&mut line, 0.001, 1.0);
    let expected: Vec<(f64, String)> = [
        (0, 0.0, 0),
        (1, 12.5, 1),
        (2, 40.0, 1),
        (4, 80.25, 1),
        (5, 3.0, 1),
        (6, 0.0, 0),
    ]
    .iter()
    .map(|&(k, rpm, pin)| (k as f64 / 10.0, format!("RPM {rpm:.3} PIN {pin}")))
    .collect();
    assert_eq!(sent.len(), expected.len());
    for ((t, text), (want_t, want)) in sent.iter().zip(&expected) {
        assert!((t - want_t).abs() < 1e-9, "{t} vs {want_t}");
        assert_eq!(text, want);
    }
    assert!(line.is_idle());
    assert_eq!(line.counters().pin_changes_delayed, 0);
}

/// A linear ramp published as 1 kHz breakpoints goes out at 10 Hz, each line the ramp's
/// average over its 0.1 s: the value at the interval's middle.
#[test]
fn fast_linear_commands_become_exact_interval_averages() {
    let mut line = ScrewLine::new(template("RPM {rpm} PIN {pin}"), 10.0, Hold::FirstOrder);
    for k in 0..=1000 {
        line.push(k as f64 / 1000.0, k as f64 / 10.0, true, 1)
            .unwrap();
    }
    let sent = run(&mut line, 0.001, 1.5);
    let rpms: Vec<f64> = sent.iter().map(|(_, t)| rpm_of(t)).collect();
    let expected: Vec<f64> = (0..10)
        .map(|k| 5.0 + 10.0 * k as f64)
        .chain([100.0])
        .collect();
    assert_eq!(rpms, expected);
    for (k, (t, _)) in sent.iter().enumerate() {
        assert!((t - k as f64 / 10.0).abs() < 1e-9, "{t}");
    }
}

/// A pin change inside a line's interval waits for the next line (counted), and the line's
/// rpm carries the interval's material.
#[test]
fn a_pin_change_within_the_rate_waits_for_the_next_line() {
    let mut line = ScrewLine::new(template(DEFAULT_TEMPLATE), 10.0, Hold::ZeroOrder);
    line.push(0.0, 100.0, true, 1).unwrap();
    line.push(0.05, 0.0, false, 2).unwrap();
    let sent = run(&mut line, 0.001, 0.3);
    assert_eq!(
        sent,
        [
            (0.0, "RPM 50.0 PIN 1\r\n".to_string()),
            (0.1, "RPM 0.0 PIN 0\r\n".to_string())
        ]
    );
    let c = line.counters();
    assert_eq!(c.pin_changes_delayed, 1);
    assert!((c.worst_pin_delay_s - 0.05).abs() < 1e-12);
}

/// In a hold the screw follows σ and the pin closes; the rate limit still holds; an
/// emergency stop goes out at once.
#[test]
fn holds_scale_the_screw_and_a_stop_goes_out_at_once() {
    let mut line = ScrewLine::new(template(DEFAULT_TEMPLATE), 10.0, Hold::ZeroOrder);
    line.push(0.0, 60.0, true, 1).unwrap();
    let at = |machine_s: f64, plan_s: f64, feed: f64, pin_allowed: bool| LineClock {
        machine_s,
        plan_s,
        feed,
        pin_allowed,
    };
    let text = |polled: Option<(String, f64)>| polled.map(|(t, _)| t);
    assert_eq!(
        text(line.poll(at(0.0, 0.0, 1.0, true))).as_deref(),
        Some("RPM 60.0 PIN 1\r\n")
    );
    // Slowing, pin still open: too soon after the last line, it waits; then σ·rpm.
    assert_eq!(line.poll(at(0.05, 0.05, 0.5, true)), None);
    assert_eq!(
        text(line.poll(at(0.1, 0.09, 0.5, true))).as_deref(),
        Some("RPM 30.0 PIN 1\r\n")
    );
    // Held at rest (σ 0, the pin closed): said at once, rate or not.
    assert_eq!(
        text(line.poll(at(0.12, 0.1, 0.0, false))).as_deref(),
        Some("RPM 0.0 PIN 0\r\n")
    );
    // A resume: the pin reopens and the screw follows σ, a period after the last line.
    assert_eq!(line.poll(at(0.2, 0.1, 0.0, true)), None, "rate: 0.1 s");
    assert_eq!(
        text(line.poll(at(0.22, 0.1, 0.0, true))).as_deref(),
        Some("RPM 0.0 PIN 1\r\n")
    );
    assert_eq!(line.stop_now(0.23).as_deref(), Some("RPM 0.0 PIN 0\r\n"));
    assert_eq!(line.stop_now(0.24), None, "already stopped");
    assert_eq!(line.poll(at(0.5, 0.5, 1.0, true)), None, "commands dropped");
    assert_eq!(line.sent(), (0.0, false));
    // A write that failed: the stop is sent again, however stopped the line thought it was.
    line.forget_sent();
    assert_eq!(line.stop_now(0.6).as_deref(), Some("RPM 0.0 PIN 0\r\n"));
    assert_eq!(line.stop_now(0.7), None);
}

/// A pin change the rate put inside a line's interval never makes a line that turns the
/// screw behind a closed pin.
#[test]
fn a_closed_pin_never_goes_with_a_turning_screw() {
    let mut line = ScrewLine::new(template(DEFAULT_TEMPLATE), 2.0, Hold::ZeroOrder);
    line.push(0.0, 0.0, false, 1).unwrap();
    line.push(0.1, 0.0, true, 2).unwrap();
    line.push(0.35, 60.0, true, 3).unwrap();
    let sent = run(&mut line, 0.001, 3.0);
    // [0, 0.5): the pin closed at the start (its opening at 0.1 waits), so rpm 0; the 9
    // rpm·s the profile asks from 0.35 are owed to the next line: 60 + 9 / 0.5 = 78.
    assert_eq!(
        sent,
        [
            (0.0, "RPM 0.0 PIN 0\r\n".to_string()),
            (0.5, "RPM 78.0 PIN 1\r\n".to_string()),
            (1.0, "RPM 60.0 PIN 1\r\n".to_string()),
        ]
    );
    // The material to 3 s is the profile's: 60 rpm from 0.35 s.
    let told: f64 = 78.0 * 0.5 + 60.0 * 2.0;
    assert!((told - 60.0 * (3.0 - 0.35)).abs() < 1e-9);
}

#[test]
fn bad_commands_are_refused_with_their_line() {
    let mut line = ScrewLine::new(template(DEFAULT_TEMPLATE), 10.0, Hold::ZeroOrder);
    assert_eq!(
        line.push(0.0, f64::NAN, true, 3).unwrap_err().to_string(),
        "screw command of line 3: rpm NaN is not a finite number ≥ 0"
    );
    assert!(line.push(0.0, -1.0, true, 3).is_err());
    line.push(1.0, 10.0, true, 4).unwrap();
    // Within a nanosecond's rounding: the same instant.
    line.push(1.0 - 1e-9, 20.0, true, 5).unwrap();
    assert_eq!(
        line.push(0.5, 10.0, true, 6),
        Err(ScrewLineError::OutOfOrder {
            source_line: 6,
            plan_s: 0.5,
            previous_s: 1.0
        })
    );
}

proptest! {
    /// Whatever the commands (pin open) and however irregularly the line is polled: no two
    /// lines closer than the rate allows, and the material sent is the commanded profile's,
    /// to the template's resolution over one period.
    #[test]
    fn lines_keep_the_rate_and_the_material(
        gaps in proptest::collection::vec(0.0f64..0.3, 1..60),
        rpms in proptest::collection::vec(0.0f64..300.0, 60),
        polls in proptest::collection::vec(0.0005f64..0.02, 400),
        first_order in any::<bool>(),
        rate_hz in 2.0f64..50.0,
    ) {
        let hold = if first_order { Hold::FirstOrder } else { Hold::ZeroOrder };
        let mut line = ScrewLine::new(template("{rpm:.2} {pin}"), rate_hz, hold);
        let mut reference = ScrewLine::new(template("{rpm:.6} {pin}"), 1e9, hold);
        let mut t = 0.0;
        for (gap, rpm) in gaps.iter().zip(&rpms) {
            t += gap;
            line.push(t, *rpm, true, 0).unwrap();
            reference.push(t, *rpm, true, 0).unwrap();
        }
        let end_s = t + 1.0 + 2.0 / rate_hz;
        // (sent at, due at, rpm)
        let mut sends: Vec<(f64, f64, f64)> = Vec::new();
        let mut now = 0.0;
        let mut k = 0;
        let largest_poll_gap = polls.iter().cloned().fold(0.0, f64::max);
        while now < end_s {
            if let Some((text, late_s)) = line.poll(LineClock { machine_s: now, plan_s: now, ..FULL }) {
                prop_assert!(late_s <= largest_poll_gap + 1e-9, "{late_s} s late");
                let rpm = text.split(' ').next().unwrap().parse().unwrap();
                sends.push((now, now - late_s, rpm));
            }
            now += polls[k % polls.len()];
            k += 1;
        }
        // Due a period apart at least; sent so less the poll's lateness.
        for w in sends.windows(2) {
            prop_assert!(w[1].1 - w[0].1 >= 1.0 / rate_hz - 1e-9, "{:?}", w);
            prop_assert!(w[1].0 - w[0].0 >= 1.0 / rate_hz - largest_poll_gap - 1e-9, "{:?}", w);
        }
        prop_assert_eq!(line.counters().lines_overtaken, 0);
        // Held from when each was due: the commanded material, to the resolution (0.01 rpm):
        // a debt a line cannot say is forgiven, and a held value is rounded for as long as
        // it is held.
        let sent: f64 = sends
            .iter()
            .enumerate()
            .map(|(i, (_, due, rpm))| rpm * (sends.get(i + 1).map_or(end_s, |n| n.1) - due))
            .sum();
        let commanded = reference.integral(0.0, end_s);
        prop_assert!(
            (sent - commanded).abs() <= 0.005 * end_s + 1e-9 * commanded.max(1.0),
            "sent {sent} rpm·s, commanded {commanded}"
        );
    }
}

/// Polled exactly on the line starts (no poll lateness), the material of every line is the
/// profile's to its resolution: a burst of commands averaged into one line, then held.
#[test]
fn polled_on_time_the_material_is_exact() {
    let mut line = ScrewLine::new(template("{rpm:.1} {pin}"), 4.0, Hold::ZeroOrder);
    let commands = [(0.0, 10.0), (0.01, 200.0), (0.02, 33.3), (0.4, 0.0)];
    for (t, rpm) in commands {
        line.push(t, rpm, true, 0).unwrap();
    }
    let sent = run(&mut line, 0.0025, 2.0);
    // [0, 0.25): (10·0.01 + 200·0.01 + 33.3·0.23)/0.25 = 39.036 → 39.0 (0.009 owed);
    // [0.25, 0.5): 33.3·0.15/0.25 + 0.009/0.25 = 20.016 → 20.0; [0.5, 0.75): the 0.004
    // rpm·s still owed is less than half a step over the period: 0.0.
    let got: Vec<(f64, f64)> = sent
        .iter()
        .map(|(t, s)| (*t, s.split(' ').next().unwrap().parse().unwrap()))
        .collect();
    assert_eq!(got, [(0.0, 39.0), (0.25, 20.0), (0.5, 0.0)]);
}

/// A line resent within its interval (the feed changed) and the next one held back by the
/// rate: the one after that still keeps a period from it.
#[test]
fn a_held_back_line_does_not_let_the_next_one_follow_at_once() {
    let mut line = ScrewLine::new(template("{rpm:.1} {pin}"), 10.0, Hold::ZeroOrder);
    line.push(0.0, 50.0, true, 0).unwrap();
    for k in 0..30 {
        line.push(0.5 + 0.1 * k as f64 + 0.001, 10.0 + k as f64, true, 0)
            .unwrap();
    }
    let mut sends = Vec::new();
    for k in 0..=3000 {
        let t = k as f64 / 1000.0;
        // σ ramps back to 1 by t = 0.5: the line in force is resent at 0.5.
        let feed = (t / 0.5).min(1.0);
        if line
            .poll(LineClock {
                machine_s: t,
                plan_s: t,
                feed,
                pin_allowed: true,
            })
            .is_some()
        {
            sends.push(t);
        }
    }
    // A period apart, less the 1 ms poll's lateness of the earlier line.
    assert!(sends.len() > 20);
    for w in sends.windows(2) {
        assert!(w[1] - w[0] >= 0.099 - 1e-9, "{:?}", w);
    }
}

/// What a line needs of the serial line: the longest line (at 1,000 rpm) times the rate, in
/// bits with the framing's start, parity and stop bits.
#[test]
fn the_bits_a_second_a_line_needs() {
    let t = template(DEFAULT_TEMPLATE);
    assert_eq!(t.render(1000.0, true), "RPM 1000.0 PIN 1\r\n");
    // 18 characters, 10 lines a second, 8N1 (10 bits a character).
    assert_eq!(t.bits_per_s(10.0, 10), 1800.0);
    // The longer pin word counts: "ON"/"OFF".
    let t = template("S{millirpm};P{pin:ON/OFF}\\r");
    assert_eq!(t.render(1000.0, false), "S1000000;POFF\r");
    assert_eq!(t.bits_per_s(4.0, 11), 4.0 * 14.0 * 11.0);
}
