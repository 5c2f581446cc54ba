//! `polar-cell print` end to end over DDS (run inside a private network namespace by
//! tests/run-all.sh): every move reaches the bag exactly once and in order.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;

use cell_bag::read_bag;
use polar_cell_msgs::{cdr, GcodeMove, Log};

/// `polar-cell print GCODE --bag BAG --no-progress EXTRA…` on DDS domain `domain` (tests run
/// in parallel: each uses its own domain so their nodes never meet): success and stderr.
/// A dry run unless EXTRA sets a `--speed`.
fn run_print(domain: u16, gcode: &Path, bag: &Path, extra: &[&str]) -> (bool, String) {
    let dry_run: &[&str] = if extra.contains(&"--speed") {
        &[]
    } else {
        &["--dry-run"]
    };
    let out = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
        .env("ROS_DOMAIN_ID", domain.to_string())
        .arg("print")
        .arg(gcode)
        .arg("--bag")
        .arg(bag)
        .arg("--no-progress")
        .args(dry_run)
        .args(extra)
        .output()
        .expect("running polar-cell");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// These tests run one at a time: each is a whole node graph (the million-move dry run keeps
/// both cores busy for minutes), and beside another one a recorder fell behind a dry run's
/// keep-last histories (21,532 of 5 million samples) or an executed print missed its pace. They
/// test what the cell does, not how two of it share two cores.
fn one_print_at_a_time() -> std::sync::MutexGuard<'static, ()> {
    static PRINTS: std::sync::Mutex<()> = std::sync::Mutex::new(());
    PRINTS
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// A G-code file of the original printer (`../shared/fixtures/gcode/`).
fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/fixtures/gcode")
        .join(name)
}

/// A new directory for one test's files, named after the test and this process.
fn scratch_dir(label: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("polar-cell-{label}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A print that must succeed: its stderr.
fn print(domain: u16, gcode: &Path, bag: &Path, extra: &[&str]) -> String {
    let (ok, stderr) = run_print(domain, gcode, bag, extra);
    assert!(ok, "polar-cell print failed:\n{stderr}");
    stderr
}

/// Sequence numbers of `/gcode/moves` in file order, and the bag's count for the topic.
fn recorded_moves(bag: &Path) -> (Vec<u64>, u64) {
    let bytes = std::fs::read(bag).unwrap();
    let contents = read_bag(&bytes).unwrap();
    let count = contents
        .info
        .topics
        .iter()
        .find(|t| t.name == "/gcode/moves")
        .map(|t| t.message_count)
        .unwrap();
    let mut seqs = Vec::new();
    for m in contents.messages().unwrap() {
        let m = m.unwrap();
        if m.topic == "/gcode/moves" {
            seqs.push(cdr::decode::<GcodeMove>(&m.data).unwrap().sequence);
        }
    }
    (seqs, count)
}

#[test]
fn a_million_moves_stream_with_zero_loss_in_order() {
    let _one_at_a_time = one_print_at_a_time();
    const MOVES: u64 = 1_000_000;
    let dir = scratch_dir("million");
    let gcode = dir.join("million.gcode");
    let mut f = std::io::BufWriter::new(std::fs::File::create(&gcode).unwrap());
    for i in 0..MOVES {
        let a = i as f64 * 0.01;
        writeln!(
            f,
            "G1 X{:.3} Y{:.3} E{:.4} F3000",
            30.0 * a.cos(),
            30.0 * a.sin(),
            i as f64 * 0.01
        )
        .unwrap();
    }
    drop(f);
    let bag = dir.join("million.mcap");
    let log = print(41, &gcode, &bag, &[]);
    let (seqs, count) = recorded_moves(&bag);
    std::fs::remove_dir_all(&dir).ok();
    assert_eq!(count, MOVES, "{log}");
    assert_eq!(seqs.len() as u64, MOVES);
    assert!(
        seqs.iter().enumerate().all(|(i, &s)| s == i as u64),
        "out of order or duplicated"
    );
}

#[test]
fn small_window_forces_flow_control_and_still_loses_nothing() {
    let _one_at_a_time = one_print_at_a_time();
    let fixture = fixture("polartest.gcode");
    let dir = scratch_dir("window");
    let bag = dir.join("w.mcap");
    let log = print(42, &fixture, &bag, &["--ros-args", "-p", "window:=3"]);
    let (seqs, count) = recorded_moves(&bag);
    // Three moves fill the window: the streamer says moves wait for acknowledgements (the
    // screw driver then cuts what it has), and the end of the file comes only with all 1,766.
    let progress: Vec<polar_cell_msgs::GcodeProgress> = topic_messages(&bag, "/gcode/progress");
    let waiting = progress.iter().filter(|p| p.moves_waiting).count();
    assert!(
        waiting > 0,
        "no report of moves waiting in {} reports",
        progress.len()
    );
    assert_file_end_told_right_and_no_instant_pin_closing(&bag, 1766);
    // A dry run has no machine node, yet its bag has the cell's description (the
    // planner's URDF), once.
    let description: Vec<polar_cell_msgs::StringMsg> = topic_messages(&bag, "/robot_description");
    assert_eq!(description.len(), 1);
    assert!(description[0].data.contains("<robot name=\"polar_cell\""));
    std::fs::remove_dir_all(&dir).ok();
    assert_eq!(count, 1766, "{log}");
    assert_eq!(seqs, (0..1766).collect::<Vec<u64>>());
    // No node closes its participant under live endpoints (RustDDS then logs "Cannot remove
    // … Disconnected" for each). Under load RustDDS may still log "… Full" when its event
    // loop is too busy to take a removal within 20 ms; that one is its own.
    assert!(!log.contains("TrySendError::Disconnected"), "{log}");
}

/// Stderr of a `print` of finger.gcode with these ROS arguments that must fail.
fn failing_print(ros_args: &[&str]) -> String {
    let fixture = fixture("finger.gcode");
    let extra: Vec<&str> = ["--ros-args"].iter().chain(ros_args).copied().collect();
    let (ok, stderr) = run_print(43, &fixture, Path::new("/dev/null"), &extra);
    assert!(!ok, "{stderr}");
    stderr
}

#[test]
fn unknown_parameter_is_an_error_that_names_it() {
    let _one_at_a_time = one_print_at_a_time();
    let stderr = failing_print(&["-p", "windw:=3"]);
    assert!(
        stderr.contains("-p windw:=3: no node of this process declares `windw`"),
        "{stderr}"
    );
    let stderr = failing_print(&["-p", "gcode_streamer:window:=many"]);
    assert!(
        stderr.contains("parameter `window` is integer, got string `many`"),
        "{stderr}"
    );
}

/// A file whose very last move leaves the arm's reach is refused by the pre-flight, naming the
/// line, the joint and where it would go — before any node starts: no bag is even created.
/// `--no-preflight` starts the print, which then fails at that move.
#[test]
fn a_file_leaving_the_reach_at_its_end_is_refused_before_anything_moves() {
    let _one_at_a_time = one_print_at_a_time();
    let fixture = fixture("polartest.gcode");
    let dir = scratch_dir("preflight");
    let gcode = dir.join("beyond.gcode");
    let mut text = std::fs::read_to_string(&fixture).unwrap();
    let last_line = text.lines().count() + 1;
    text.push_str("G1 X120 Y120 F3000\n"); // r = 169.7 mm > 150 mm
    std::fs::write(&gcode, text).unwrap();
    let bag = dir.join("refused.mcap");
    let (ok, stderr) = run_print(44, &gcode, &bag, &[]);
    assert!(!ok, "{stderr}");
    assert!(stderr.contains("pre-flight refuses the print"), "{stderr}");
    assert!(
        stderr.contains(&format!("(line {last_line}): arm_r would reach 0.169706")),
        "{stderr}"
    );
    assert!(!bag.exists(), "nothing started, no bag");
    // The same through `check`.
    let out = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
        .arg("check")
        .arg(&gcode)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!out.status.success());
    assert!(
        stderr.contains(&format!("(line {last_line}): arm_r")),
        "{stderr}"
    );
    // Without it the print starts, and the planner stops at that move after the whole part.
    let (ok, stderr) = run_print(44, &gcode, &bag, &["--no-preflight"]);
    assert!(!ok, "{stderr}");
    assert!(
        stderr.contains(&format!("(line {last_line}): arm_r")),
        "{stderr}"
    );
    assert!(bag.exists(), "this time the print had started");
    // Executed, with the move a third into the part: the planner fails while the machine
    // runs, and the machine stops on the path at the end of what was planned (dropping it
    // would stop a real MCU at once, mid-move).
    let source = std::fs::read_to_string(&fixture).unwrap();
    let lines: Vec<&str> = source.lines().collect();
    let at = lines.len() / 3;
    let mut text = lines[..at].join("\n");
    text.push_str("\nG1 X120 Y120 F3000\n");
    text.push_str(&lines[at..].join("\n"));
    std::fs::write(&gcode, text).unwrap();
    let (ok, stderr) = run_print(44, &gcode, &bag, &["--no-preflight", "--speed", "20"]);
    assert!(!ok, "{stderr}");
    assert!(
        stderr.contains(&format!("(line {}): arm_r", at + 1))
            && stderr.contains("; cancelled: stopped on the path at line"),
        "{stderr}"
    );
    let states = topic_messages::<polar_cell_msgs::JointState>(&bag, "/joint_states");
    let last = states.last().expect("executed joint states");
    assert!(states.len() > 10, "{} states", states.len());
    assert!(
        last.velocity.iter().all(|v| v.abs() < 1e-9),
        "at rest at the end: {:?}",
        last.velocity
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// The pre-flight of a good file reports its machine time before the print starts.
#[test]
fn the_preflight_reports_the_machine_time_of_a_good_file() {
    let _one_at_a_time = one_print_at_a_time();
    let fixture = fixture("finger.gcode");
    let out = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
        .arg("check")
        .arg(&fixture)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(out.status.success(), "{stdout}");
    // finger's plan with the screw's limits: 168.1 s (the planner's own tests: 165.8 s
    // without them).
    assert!(
        stdout.contains("pre-flight passed: 1778 moves, 0:02:48.055 of machine time"),
        "{stdout}"
    );
}

/// Decoded messages of one topic of a bag, in log order.
fn topic_messages<T: polar_cell_msgs::RosMessage>(bag: &Path, topic: &str) -> Vec<T> {
    let bytes = std::fs::read(bag).unwrap();
    let contents = read_bag(&bytes).unwrap();
    contents
        .messages()
        .unwrap()
        .map(|m| m.unwrap())
        .filter(|m| m.topic == topic)
        .map(|m| cdr::decode::<T>(&m.data).unwrap())
        .collect()
}

/// The cell's steps per rad of `bed_theta`, per m of `arm_r` and `z` (the defaults).
const STEPS_PER_UNIT: [f64; 3] = [32000.0 / std::f64::consts::TAU, 80_000.0, 400_000.0];

/// Where the plan's steps end: each axis's signed steps summed over `segments`.
fn end_steps(segments: &[polar_cell_msgs::StepSegment]) -> [i64; 3] {
    std::array::from_fn(|k| {
        segments
            .iter()
            .map(|s| s.step_counts[k] as i64 * s.directions[k] as i64)
            .sum()
    })
}

/// The executed print: finger.gcode at 40× machine pace. Its bag's `/joint_states` are the
/// executor's: all four URDF joints on a regular 50 Hz grid of machine time, within every
/// URDF velocity limit, ending exactly where the step segments sum to; `/tf`, `/tf_static`
/// and `/robot_description` are there; and the executed time matches the plan's.
#[test]
fn an_executed_print_records_the_executed_joints_at_50_hz() {
    let _one_at_a_time = one_print_at_a_time();
    use polar_cell_msgs::{JointState, StepSegment, StringMsg, TFMessage};
    let fixture = fixture("finger.gcode");
    let bag = std::env::temp_dir().join(format!("polar-cell-exec-{}.mcap", std::process::id()));
    // At 40× the default 2 s horizon is 50 ms of the test's time; on a loaded CI machine a
    // starved planner could fall behind it. Twenty seconds of plan is half a second here.
    let stderr = print(
        60,
        &fixture,
        &bag,
        &[
            "--speed",
            "40",
            "--ros-args",
            "-p",
            "cell_executor:horizon_s:=20.0",
        ],
    );
    // "executed N step segments in m:ss.s of machine time from the first step (T s; planned P s)"
    let executed_line = stderr
        .lines()
        .find(|l| l.contains("executed 4074 step segments"))
        .unwrap_or_else(|| panic!("{stderr}"));
    let number_after = |key: &str| -> f64 {
        let rest = &executed_line[executed_line.find(key).unwrap() + key.len()..];
        rest.split(|c: char| c != '.' && !c.is_ascii_digit())
            .find(|t| !t.is_empty())
            .unwrap()
            .parse()
            .unwrap()
    };
    let (executed_s, planned_s) = (number_after("step ("), number_after("planned "));
    // Start and end are placed by the plan clock, not at the tick that noticed them (a tick
    // is 0.1 ms of wall time, 4 ms of machine time at 40×, or much longer on a loaded CI).
    assert!(
        (executed_s - planned_s).abs() < 0.01,
        "executed {executed_s} s, planned {planned_s} s"
    );
    assert!(executed_line.contains(", 0 underruns"), "{executed_line}");

    let states: Vec<JointState> = topic_messages(&bag, "/joint_states");
    assert!(states.len() as f64 >= planned_s / 0.02, "{}", states.len());
    for w in states.windows(2) {
        let dt = w[1].header.stamp.as_nanos() - w[0].header.stamp.as_nanos();
        assert_eq!(dt, 20_000_000, "50 Hz of machine time");
    }
    let limits = [6.0, 0.2, 0.02, std::f64::consts::PI * 10.0];
    for s in &states {
        assert_eq!(s.name, ["bed_theta", "arm_r", "z", "screw"]);
        for (v, limit) in s.velocity.iter().zip(limits) {
            assert!(v.abs() <= limit * (1.0 + 1e-9), "{v} beyond {limit}");
        }
    }
    let segments: Vec<StepSegment> = topic_messages(&bag, "/polar/steps");
    assert_eq!(segments.len(), 4074);
    let last = states.last().unwrap();
    for (k, steps) in end_steps(&segments).into_iter().enumerate() {
        assert_eq!(
            last.position[k],
            steps as f64 / STEPS_PER_UNIT[k],
            "joint {k}"
        );
        assert_eq!(last.velocity[k], 0.0);
    }
    let tf: Vec<TFMessage> = topic_messages(&bag, "/tf");
    // Every sample's transforms, stamped as its joints: the same stamps in the same order.
    let state_stamps: Vec<i64> = states.iter().map(|s| s.header.stamp.as_nanos()).collect();
    let tf_stamps: Vec<i64> = (tf.iter())
        .map(|t| t.transforms[0].header.stamp.as_nanos())
        .collect();
    if tf_stamps != state_stamps {
        let first_difference = state_stamps
            .iter()
            .zip(&tf_stamps)
            .position(|(a, b)| a != b);
        panic!(
            "{} /joint_states, {} /tf; first difference at {first_difference:?}; \
             /joint_states {:?}..{:?}, /tf {:?}..{:?}",
            state_stamps.len(),
            tf_stamps.len(),
            state_stamps.first(),
            state_stamps.last(),
            tf_stamps.first(),
            tf_stamps.last()
        );
    }
    assert_eq!(tf[0].transforms.len(), 4);
    assert_eq!(topic_messages::<TFMessage>(&bag, "/tf_static").len(), 1);
    let description: Vec<StringMsg> = topic_messages(&bag, "/robot_description");
    assert_eq!(description.len(), 1);
    assert!(description[0].data.contains("<robot name=\"polar_cell\""));
    std::fs::remove_file(&bag).ok();
}

/// Ctrl-C while executing stops on the path and finishes the bag; the machine is at rest
/// (every executed velocity 0) with the screw stopped. A second Ctrl-C during that stop stops
/// at once. At 0.1× machine pace, so the stop (tens of ms of machine time) spans hundreds of
/// ms of the test's time. The same on the MCU emulator, which a terminal's Ctrl-C used to
/// kill with the print (it was in the print's process group): the print then "stopped at
/// once" on a closed line instead of on the path.
#[test]
fn ctrl_c_cancels_on_the_path_and_a_second_stops_at_once() {
    let _one_at_a_time = one_print_at_a_time();
    use polar_cell_msgs::JointState;
    let dir = scratch_dir("cancel");
    // Out along the arm, then round the bed: moving at every instant of the first seconds.
    let gcode = dir.join("circle.gcode");
    let mut text = String::from("G1 X50 Y0 F3000\n");
    for i in 1..=200 {
        let a = i as f64 * std::f64::consts::TAU / 200.0;
        text += &format!("G1 X{:.3} Y{:.3} F6000\n", 50.0 * a.cos(), 50.0 * a.sin());
    }
    std::fs::write(&gcode, text).unwrap();
    // As a terminal's Ctrl-C: SIGINT to the print's whole process group (with the MCU
    // emulator it starts, which must not die of it: the stop is the print's to make).
    for (domain, second_interrupt, device) in [
        (61u16, false, None),
        (62, true, None),
        (64, false, Some("emulator")),
    ] {
        let bag = dir.join(format!("stop-{domain}.mcap"));
        let mut command = Command::new(env!("CARGO_BIN_EXE_polar-cell"));
        command
            .env("ROS_DOMAIN_ID", domain.to_string())
            .arg("print")
            .arg(&gcode)
            .arg("--bag")
            .arg(&bag)
            .stderr(std::process::Stdio::piped());
        match device {
            None => command.args(["--no-progress", "--speed", "0.1"]),
            Some(device) => command.args(["--no-progress", "--speed", "0.5", "--device", device]),
        };
        std::os::unix::process::CommandExt::process_group(&mut command, 0);
        let child = command.spawn().unwrap();
        let group = child.id() as i32;
        std::thread::sleep(std::time::Duration::from_secs(4));
        // SAFETY: signalling our own child's process group.
        assert_eq!(unsafe { libc::killpg(group, libc::SIGINT) }, 0);
        if second_interrupt {
            std::thread::sleep(std::time::Duration::from_millis(20));
            assert_eq!(unsafe { libc::killpg(group, libc::SIGINT) }, 0);
        }
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{stderr}");
        let expected = if second_interrupt {
            "emergency stop at line"
        } else {
            "cancelled: stopped on the path at line"
        };
        assert!(stderr.contains(expected), "{stderr}");
        assert!(stderr.contains("the bag was finished"), "{stderr}");
        let states: Vec<JointState> = topic_messages(&bag, "/joint_states");
        let last = states.last().unwrap();
        assert_eq!(last.velocity, [0.0; 4], "at rest, screw stopped");
        assert!(
            states.iter().any(|s| s.velocity[1] != 0.0),
            "it moved first"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// With no file, `print` prints the built-in demo (a clone alone is enough to run the cell),
/// executed like any file.
#[test]
fn print_without_a_file_prints_the_built_in_demo() {
    let _one_at_a_time = one_print_at_a_time();
    let bag = std::env::temp_dir().join(format!("polar-cell-demo-{}.mcap", std::process::id()));
    let out = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
        .env("ROS_DOMAIN_ID", "63")
        .args(["print", "--no-progress", "--speed", "25", "--bag"])
        .arg(&bag)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("demo-vase-and-star.gcode: pre-flight passed: 735 moves"),
        "{stderr}"
    );
    assert!(stderr.contains("executed 3795 step segments"), "{stderr}");
    assert_file_end_told_right_and_no_instant_pin_closing(&bag, 735);
    std::fs::remove_file(&bag).ok();
}

/// The streamer says the file has ended only with all its moves published (a screw driver
/// told so early closes the pin mid-run), and the pin closes for an instant (closed and
/// reopened at one stamp) only at a travel move shorter than its opening delay, never inside
/// a run of extrusion (a chunk cut as if the file had ended).
fn assert_file_end_told_right_and_no_instant_pin_closing(bag: &Path, moves_in_file: u64) {
    use polar_cell_msgs::{GcodeProgress, ScrewCommand};
    let progress: Vec<GcodeProgress> = topic_messages(bag, "/gcode/progress");
    let told = progress.iter().filter(|p| p.end_of_file).count();
    assert!(told > 0, "no /gcode/progress says the file ended");
    for p in progress.iter().filter(|p| p.end_of_file) {
        assert_eq!(p.moves_published, moves_in_file, "end of file told early");
        assert!(!p.moves_waiting, "moves waiting at the end of the file");
    }
    let travel_lines: std::collections::HashSet<u32> =
        topic_messages::<GcodeMove>(bag, "/gcode/moves")
            .iter()
            .filter(|m| !m.extrude)
            .map(|m| m.source_line)
            .collect();
    let commands: Vec<ScrewCommand> = topic_messages(bag, "/screw/command");
    for w in commands.windows(2) {
        let instant_closing =
            !w[0].pin_open && w[1].pin_open && w[0].header.stamp == w[1].header.stamp;
        assert!(
            !instant_closing || travel_lines.contains(&w[0].source_line),
            "the pin closed for an instant inside a run at command {} (line {})",
            w[0].sequence,
            w[0].source_line
        );
    }
}

/// The same print on the MCU: `--device emulator` starts mcu_emulator on a pseudo-terminal
/// at the print's speed and the bridge plays the plan on it. Every segment executes, on the
/// plan's time, with no underrun; the bag's `/joint_states` are the MCU's reported counts on
/// increasing stamps (when the MCU measured them), within the URDF's velocity limits, ending
/// exactly where the step segments sum to.
#[test]
fn a_print_on_the_mcu_emulator_executes_every_step() {
    let _one_at_a_time = one_print_at_a_time();
    use polar_cell_msgs::{JointState, StepSegment};
    let fixture = fixture("finger.gcode");
    let bag = std::env::temp_dir().join(format!("polar-cell-mcu-{}.mcap", std::process::id()));
    let stderr = print(
        61,
        &fixture,
        &bag,
        &[
            "--speed",
            "10",
            "--device",
            "emulator",
            // 0.6 s of the test's time in hand (the default 2 s is 0.2 s at 10×): in CI,
            // beside the other pipeline tests, a starved bridge ran the MCU dry at 2 s.
            "--ros-args",
            "-p",
            "mcu_bridge:horizon_s:=6.0",
        ],
    );
    assert!(stderr.contains("MCU emulator on /dev/pts/"), "{stderr}");
    let executed_line = stderr
        .lines()
        .find(|l| l.contains("executed 4074 step segments"))
        .unwrap_or_else(|| panic!("{stderr}"));
    assert!(executed_line.contains(", 0 underruns"), "{executed_line}");
    let states: Vec<JointState> = topic_messages(&bag, "/joint_states");
    // 168 s of the MCU's 100 Hz state reports, sampled at 50 Hz of machine time. At 10x a
    // report period is 1 ms of wall time, and a loaded machine's emulator misses some: a CI
    // run beside the other pipeline tests sampled 37 Hz. At least 25 Hz, as the interop
    // launch test asks of the same reports.
    assert!(states.len() > 4200, "{} states", states.len());
    for w in states.windows(2) {
        assert!(w[1].header.stamp.as_nanos() > w[0].header.stamp.as_nanos());
    }
    let limits = [6.0, 0.2, 0.02, std::f64::consts::PI * 10.0];
    for s in &states {
        for (v, limit) in s.velocity.iter().zip(limits) {
            // Velocities from two reports 10 ms apart: a step's rounding on top.
            assert!(v.abs() <= limit * 1.02, "{v} beyond {limit}");
        }
    }
    let segments: Vec<StepSegment> = topic_messages(&bag, "/polar/steps");
    assert_eq!(segments.len(), 4074);
    let last = states.last().unwrap();
    for (k, steps) in end_steps(&segments).into_iter().enumerate() {
        let reported = (last.position[k] * STEPS_PER_UNIT[k]).round() as i64;
        assert_eq!(reported, steps, "joint {k}");
    }
    std::fs::remove_file(&bag).ok();
}

/// `/rosout` as rclcpp writes it: each node's logger name with its namespace in dots, and
/// the file, line and function of the log call in that node's code — not the runtime's one
/// logging function (every message used to say `dds.rs:321 <unknown_func>`).
#[test]
fn rosout_names_the_namespaced_logger_and_the_calling_code() {
    let _one_at_a_time = one_print_at_a_time();
    let fixture = fixture("polartest.gcode");
    let dir = scratch_dir("rosout");
    let bag = dir.join("rosout.mcap");
    print(45, &fixture, &bag, &["--ros-args", "-r", "__ns:=/bar"]);
    let bytes = std::fs::read(&bag).unwrap();
    std::fs::remove_dir_all(&dir).ok();
    let contents = read_bag(&bytes).unwrap();
    let logs: Vec<Log> = contents
        .messages()
        .unwrap()
        .map(|m| m.unwrap())
        .filter(|m| m.topic == "/rosout")
        .map(|m| cdr::decode::<Log>(&m.data).unwrap())
        .collect();
    let from = |name: &str| logs.iter().find(|l| l.name == name);
    let streamer = from("bar.gcode_streamer").expect("the streamer's log, in namespace bar");
    assert_eq!(streamer.file, "nodes/gcode_streamer/src/node.rs");
    assert_eq!(streamer.function, "gcode_streamer::node::stream");
    let planner = from("bar.polar_planner").expect("the planner's log");
    assert_eq!(planner.file, "nodes/polar_planner/src/node.rs");
    assert!(planner.function.starts_with("polar_planner::node::"));
    for log in &logs {
        assert!(log.name.starts_with("bar."), "{log:?}");
        assert!(log.line > 0 && log.file.ends_with("/node.rs"), "{log:?}");
        assert!(!log.function.contains("unknown"), "{log:?}");
        // The line holds the call.
        let source =
            std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join(&log.file)).unwrap();
        let line = source.lines().nth(log.line as usize - 1).unwrap();
        assert!(
            line.contains("cell_log!"),
            "{}:{} is `{line}`",
            log.file,
            log.line
        );
    }
}

/// The screw on its servo amplifier's own serial line (seed 000 §6.3; a pseudo-terminal
/// here, read by this test): a print on the MCU emulator tells it at most ten times a
/// second of machine time, as `RPM r PIN p` lines; the screw turns with the pin open while
/// printing and ends stopped with the pin closed; the bag's screw joint turns at the rpm the
/// line told it, and the MCU's own screw output stays idle.
#[test]
fn a_print_on_the_mcu_tells_the_screw_amplifier_on_its_own_serial_line() {
    let _one_at_a_time = one_print_at_a_time();
    use polar_cell_msgs::JointState;
    let dir = scratch_dir("screw-line");
    let gcode = dir.join("start.gcode");
    let source = std::fs::read_to_string(fixture("polartest.gcode")).unwrap();
    let start: Vec<&str> = source.lines().take(400).collect();
    std::fs::write(&gcode, start.join("\n") + "\n").unwrap();
    let (mut master, mut slave) = (0, 0);
    // SAFETY: openpty writes two descriptors; no name, termios or window size asked for.
    let opened = unsafe {
        libc::openpty(
            &mut master,
            &mut slave,
            std::ptr::null_mut(),
            std::ptr::null(),
            std::ptr::null(),
        )
    };
    assert_eq!(opened, 0);
    // SAFETY: `slave` is an open descriptor; ttyname's buffer is read before another call.
    let port = unsafe { std::ffi::CStr::from_ptr(libc::ttyname(slave)) }
        .to_str()
        .unwrap()
        .to_string();
    let reader = std::thread::spawn(move || {
        use std::io::Read;
        use std::os::fd::FromRawFd;
        // SAFETY: the master descriptor is this thread's alone from here on.
        let mut file = unsafe { std::fs::File::from_raw_fd(master) };
        let mut bytes = Vec::new();
        let mut buf = [0u8; 4096];
        loop {
            match file.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => bytes.extend_from_slice(&buf[..n]),
                // Every slave descriptor closed: all written has been read.
                Err(e) if e.raw_os_error() == Some(libc::EIO) => break,
                Err(e) => panic!("{e}"),
            }
        }
        String::from_utf8(bytes).unwrap()
    });
    let bag = dir.join("screw-line.mcap");
    let screw_port = format!("mcu_bridge:screw_port:={port}");
    let stderr = print(
        71,
        &gcode,
        &bag,
        &[
            "--speed",
            "10",
            "--device",
            "emulator",
            "--ros-args",
            "-p",
            &screw_port,
            "-p",
            "mcu_bridge:horizon_s:=6.0",
        ],
    );
    // SAFETY: the test's own copy of the slave side, open since openpty.
    unsafe { libc::close(slave) };
    let text = reader.join().unwrap();
    assert!(stderr.contains(", 0 underruns"), "{stderr}");
    let told: Vec<(f64, bool)> = text
        .strip_suffix("\r\n")
        .unwrap_or_else(|| panic!("{text:?}"))
        .split("\r\n")
        .map(|line| match line.split(' ').collect::<Vec<_>>()[..] {
            ["RPM", rpm, "PIN", pin] => (rpm.parse().unwrap(), pin == "1"),
            _ => panic!("{line:?}"),
        })
        .collect();
    let printing = told.iter().filter(|(rpm, pin)| *rpm > 1.0 && *pin).count();
    assert!(printing > 50, "{printing} of {} lines feed", told.len());
    assert_eq!(told.last(), Some(&(0.0, false)));
    // The bag's screw joint turns at what the line said (rad/s of rpm), nothing else.
    let states: Vec<JointState> = topic_messages(&bag, "/joint_states");
    let told_rad_s: Vec<f64> = told
        .iter()
        .map(|(rpm, _)| rpm / 60.0 * std::f64::consts::TAU)
        .collect();
    let mut turning = 0;
    for s in &states {
        let v = s.velocity[3];
        assert!(
            v == 0.0 || told_rad_s.iter().any(|t| (t - v).abs() < 1e-9),
            "screw at {v} rad/s: never told"
        );
        turning += usize::from(v > 0.0);
    }
    assert!(turning * 2 > states.len(), "{turning} of {}", states.len());
    std::fs::remove_dir_all(&dir).ok();
}
