//! The command-line tool as a shell user meets it: pipes, wrong remaps, interruptions.

use std::io::Write;
use std::os::unix::process::ExitStatusExt;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// `polar-cell bag info BAG | head` where the reader has already gone: the write fails and
/// the tool ends quietly by SIGPIPE, like any Unix tool — no panic message, no exit 101.
#[test]
fn output_into_a_closed_pipe_ends_quietly() {
    let bag = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/polartest_moves.mcap");
    let mut child = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
        .args(["bag", "info"])
        .arg(&bag)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take()); // the reader end closes before anything is written
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        out.status.signal(),
        Some(libc::SIGPIPE),
        "{:?} {stderr}",
        out.status
    );
    assert!(stderr.is_empty(), "{stderr}");
}

/// An unprefixed `-r __node:=NAME` would name every node of the print alike: refused at once.
#[test]
fn an_unprefixed_node_rename_is_refused_at_once() {
    let fixture =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/fixtures/gcode/polartest.gcode");
    let started = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
        .env("ROS_DOMAIN_ID", "45")
        .arg("print")
        .arg(&fixture)
        .args([
            "--bag",
            "/dev/null",
            "--no-progress",
            "--ros-args",
            "-r",
            "__node:=foo",
        ])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("rename one with -r NODE:__node:=foo (NODE: gcode_streamer,"),
        "{stderr}"
    );
    assert!(started.elapsed() < Duration::from_secs(5));
}

/// A print stopped by SIGINT finishes its bag and exits non-zero.
#[test]
fn an_interrupted_print_finishes_its_bag_and_exits_non_zero() {
    let dir = std::env::temp_dir().join(format!("polar-cell-sigint-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let gcode = dir.join("long.gcode");
    let mut f = std::io::BufWriter::new(std::fs::File::create(&gcode).unwrap());
    for i in 0..400_000 {
        let a = i as f64 * 0.01;
        writeln!(f, "G1 X{:.3} Y{:.3} F3000", 30.0 * a.cos(), 30.0 * a.sin()).unwrap();
    }
    drop(f);
    let bag = dir.join("interrupted.mcap");
    let child = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
        .env("ROS_DOMAIN_ID", "46")
        .arg("print")
        .arg(&gcode)
        .arg("--bag")
        .arg(&bag)
        .args(["--no-progress", "--no-preflight", "--dry-run"])
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(1500));
    // SAFETY: sending a signal to our own child process.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGINT) }, 0);
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("interrupted before the end of"), "{stderr}");
    let bytes = std::fs::read(&bag).unwrap();
    let contents = cell_bag::read_bag(&bytes).unwrap();
    let moves = contents
        .info
        .topics
        .iter()
        .find(|t| t.name == "/gcode/moves")
        .map_or(0, |t| t.message_count);
    assert!(moves > 0 && moves < 400_000, "{moves} moves recorded");
    std::fs::remove_dir_all(&dir).ok();
}

/// A bag that cannot be written stops the print with the reason, naming the bag. On a full
/// device (`/dev/full`) that is at once, before anything moves. When the disk fills mid-print
/// (here: a file-size limit, `RLIMIT_FSIZE`, with `SIGXFSZ` ignored so a write past it fails
/// with EFBIG), the machine stops on the path — it used to hang: the recorder's taps died with
/// its writer, the streamer waited for their acknowledgements, and nothing said why.
#[test]
fn a_bag_that_cannot_be_written_stops_the_print_with_the_reason() {
    let gcode =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/fixtures/gcode/polartest.gcode");
    let dir = std::env::temp_dir().join(format!("polar-cell-full-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let limited = dir.join("limited.mcap");
    let cases: [(&str, &Path, &[&str], Option<u64>); 3] = [
        (
            "full device",
            Path::new("/dev/full"),
            &["--speed", "20"],
            None,
        ),
        ("executing", &limited, &["--speed", "20"], Some(16 * 1024)),
        ("dry run", &limited, &["--dry-run"], Some(16 * 1024)),
    ];
    for (case, bag, extra, file_size_limit) in cases {
        let started = Instant::now();
        let mut command = Command::new(env!("CARGO_BIN_EXE_polar-cell"));
        command
            .env("ROS_DOMAIN_ID", "47")
            .arg("print")
            .arg(&gcode)
            .arg("--bag")
            .arg(bag)
            .arg("--no-progress")
            .args(extra)
            .stderr(Stdio::piped());
        if let Some(bytes) = file_size_limit {
            use std::os::unix::process::CommandExt as _;
            // SAFETY: between fork and exec, only async-signal-safe calls on this process.
            unsafe {
                command.pre_exec(move || {
                    libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
                    let limit = libc::rlimit {
                        rlim_cur: bytes,
                        rlim_max: bytes,
                    };
                    if libc::setrlimit(libc::RLIMIT_FSIZE, &limit) != 0 {
                        return Err(std::io::Error::last_os_error());
                    }
                    Ok(())
                });
            }
        }
        let mut child = command.spawn().unwrap();
        // Not for ever: a hang is the failure this test is about.
        while child.try_wait().unwrap().is_none() {
            if started.elapsed() > Duration::from_secs(60) {
                child.kill().unwrap();
                panic!("{case}: still running after 60 s");
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{case}: {stderr}");
        assert!(
            stderr.contains(&format!("the bag {} could not be written", bag.display())),
            "{case}: {stderr}"
        );
        match case {
            // Refused before the graph started: nothing moved, nothing to stop.
            "full device" => assert!(
                stderr.contains("No space left on device")
                    && !stderr.contains("stopped on the path"),
                "{stderr}"
            ),
            _ => assert!(stderr.contains("File too large"), "{case}: {stderr}"),
        }
        if case == "executing" {
            assert!(
                stderr.contains("cancelled: stopped on the path at line"),
                "{stderr}"
            );
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// `polar-cell mechanism` with inputs that are wrong: the message names what is wrong (today's
/// had a leg length for a tip a million km away, "tip z" for a NaN angle, and no file or line
/// for a binary CL file).
#[test]
fn mechanism_messages_name_what_is_wrong() {
    let run = |args: &[&str]| -> String {
        let out = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
            .arg("mechanism")
            .args(args)
            .env("RUST_BACKTRACE", "0")
            .output()
            .unwrap();
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let err = run(&["ik", "--tip-mm", "1e9,0,0"]);
    assert!(
        err.contains("tool tip X = 1000000000 mm is out of reach"),
        "{err}"
    );
    let err = run(&[
        "ik",
        "--z",
        "393",
        "--theta1-deg",
        "nan",
        "--theta2-deg",
        "10",
    ]);
    assert!(err.contains("--theta1-deg is NaN"), "{err}");
    let dir = std::env::temp_dir().join(format!("polar-cell-cl-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cl = dir.join("binary.cl");
    std::fs::write(&cl, b"GOTO/1,2,3\nGOTO/\xff\x00\n").unwrap();
    let err = run(&["cl", cl.to_str().unwrap()]);
    assert!(
        err.contains(&format!(
            "{}:2:6: byte 0xff is not UTF-8 text",
            cl.display()
        )),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// `check` plans with the parameters `print` would give its nodes: a global `-p` of another
/// node is no error, and the screw driver's top speed slows the plan as in a print.
#[test]
fn check_plans_with_the_prints_parameters() {
    let fixture =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/fixtures/gcode/finger.gcode");
    let check = |ros_args: &[&str]| -> String {
        let fixture = fixture.to_str().unwrap();
        polar_cell_ok(&[&["check", fixture, "--ros-args"], ros_args].concat())
    };
    assert!(check(&["-p", "window:=3"]).contains("1778 moves, 0:02:48.055 of machine time"));
    assert!(check(&["-p", "screw_driver:max_rpm:=100"])
        .contains("1778 moves, 0:05:25.201 of machine time"));
}

/// A parameter for a node the print does not run is refused before anything starts: the
/// virtual executor's on a print on the MCU (it was dropped without a word), a name the
/// node does not declare, and a node that does not exist.
#[test]
fn print_refuses_a_parameter_no_node_of_it_takes() {
    let refused = |extra: &[&str], ros_args: &[&str]| -> String {
        let out = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
            .args(["print", "--no-progress", "--bag", "/dev/null"])
            .args(extra)
            .arg("--ros-args")
            .args(ros_args)
            .env("RUST_BACKTRACE", "0")
            .output()
            .unwrap();
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let nodes = "(its nodes: bag_recorder, gcode_streamer, polar_planner, screw_driver, ";
    let stderr = refused(
        &["--device", "emulator"],
        &["-p", "cell_executor:horizon_s:=1.0"],
    );
    assert!(
        stderr.contains(&format!(
            "-p cell_executor:horizon_s:=1.0: this print runs no node `cell_executor` \
             {nodes}mcu_bridge)"
        )),
        "{stderr}"
    );
    let stderr = refused(&[], &["-p", "mcu_bridge:horizon_s:=1.0"]);
    assert!(
        stderr.contains(&format!("runs no node `mcu_bridge` {nodes}cell_executor)")),
        "{stderr}"
    );
    let stderr = refused(&[], &["-p", "polar_planner:baud:=9600"]);
    assert!(
        stderr.contains("node `polar_planner` declares no parameter `baud`"),
        "{stderr}"
    );
}

/// stdout of `polar-cell ARGS`, which must succeed (else its output is the failure).
fn polar_cell_ok(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{args:?}: {stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// `mechanism cl --calibration` gives each CL point the calibration's whole command, as
/// `mechanism ik --calibration` does for the same tip: its legs and the table that absorbs
/// the simulated machine's X/Y error (it paired corrected legs with the nominal table, the
/// tip off by that error).
#[test]
fn mechanism_cl_with_a_calibration_commands_the_corrected_table() {
    let dir = std::env::temp_dir().join(format!("polar-cell-cl-cal-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = |name: &str| dir.join(name).to_str().unwrap().to_string();
    let run = |args: &[&str]| polar_cell_ok(&[&["mechanism"], args].concat());
    let (measurements, calibration, cl) = (path("m.csv"), path("cal.json"), path("part.cl"));
    run(&[
        "simulate",
        "--seed",
        "3",
        "--poses",
        "40",
        "--out",
        &measurements,
    ]);
    run(&[
        "calibrate",
        "--measurements",
        &measurements,
        "--out",
        &calibration,
    ]);
    std::fs::write(&cl, "5,5,250,0,0,-1,s\n6,5,250,0,0,-1,e\n").unwrap();
    let json = |text: String| -> serde_json::Value { serde_json::from_str(&text).unwrap() };
    let post = json(run(&["cl", &cl, "--calibration", &calibration, "--json"]));
    let ik = json(run(&[
        "ik",
        "--tip-mm",
        "5,5,250",
        "--calibration",
        &calibration,
        "--json",
    ]));
    let work = post["commands"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["tip_mm"] == serde_json::json!([5.0, 5.0, 250.0]))
        .unwrap_or_else(|| panic!("{post}"));
    let table = |v: &serde_json::Value| -> Vec<f64> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let corrected = table(&ik["calibrated"]["table_mm"]);
    let nominal = table(&ik["table_mm"]);
    assert!(
        corrected
            .iter()
            .zip(&nominal)
            .any(|(c, n)| (c - n).abs() > 0.01),
        "the simulated machine has no X/Y error here: {corrected:?} {nominal:?}"
    );
    assert_eq!(table(&work["table_mm"]), corrected, "{work}");
    assert_eq!(work["leg_lengths_mm"], ik["calibrated"]["leg_lengths_mm"]);
    std::fs::remove_dir_all(&dir).ok();
}

/// `bag play` refuses what it cannot do before it starts a node: a topic the bag lacks (a
/// typo would play nothing and succeed), a rate or a wait that no clock takes.
#[test]
fn bag_play_refuses_a_missing_topic_and_impossible_numbers() {
    let bag = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden/polartest_moves.mcap");
    let refused = |extra: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
            .args(["bag", "play"])
            .arg(&bag)
            .args(extra)
            .env("ROS_DOMAIN_ID", "48")
            .output()
            .unwrap();
        assert!(!out.status.success(), "{extra:?}");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let why = refused(&["--topics", "/gcode/move"]);
    assert!(
        why.contains("no topic /gcode/move in the bag (it has /gcode/moves"),
        "{why}"
    );
    for (arg, value) in [
        ("--rate", "1e-18"),
        ("--rate", "0"),
        ("--wait-subscribers-s", "inf"),
        ("--deliver-timeout-s", "1e20"),
        ("--deliver-timeout-s", "NaN"),
    ] {
        let why = refused(&[arg, value]);
        assert!(
            why.contains(&format!("invalid value '{value}' for '{arg}")),
            "{why}"
        );
    }
}

/// `bag recover` of something that is not a bag fails and leaves no output behind, so the
/// next try (with the right input) is not refused for an existing file.
#[test]
fn a_failed_recovery_leaves_no_output() {
    let dir = std::env::temp_dir().join(format!("polar-cell-recover-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let garbage = dir.join("garbage.mcap");
    std::fs::write(&garbage, b"this is not an MCAP file at all").unwrap();
    let output = dir.join("recovered.mcap");
    let out = Command::new(env!("CARGO_BIN_EXE_polar-cell"))
        .args(["bag", "recover"])
        .arg(&garbage)
        .arg(&output)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(stderr.contains("recovering"), "{stderr}");
    assert!(!output.exists(), "a partial output was left");
    std::fs::remove_dir_all(&dir).ok();
}
