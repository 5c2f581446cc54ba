//! `polar-cell mechanism …`: the hybrid machining head's kinematics from the command line.
//!
//! `ik` and `fk` solve one pose, `cl` post-processes a CL file into joint commands, `urdf`
//! prints the URDF the geometry defines. `--json` prints machine-readable results; `--bag`
//! records `/mechanism/joint_states` (every URDF joint) and `/robot_description`.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context};
use cell_bag::{BagWriter, QosRecord, WriterOptions};
use clap::Subcommand;
use mechanism_kin::calib::{self, Calibration};
use mechanism_kin::cl::{self, MoveKind, PostOptions};
use mechanism_kin::kinematics::{ForwardSolver, ToolTarget};
use mechanism_kin::report::{evaluate, Evaluation};
use mechanism_kin::urdf::{joint_names, UrdfTree};
use mechanism_kin::{Geometry, Pose};
use nalgebra::Vector3;
use polar_cell_msgs::{Header, JointState, PoseStamped, RosMessage, StringMsg, Time};
use serde_json::json;

#[derive(Subcommand, Debug)]
pub enum MechanismCommand {
    /// Inverse kinematics: leg lengths, table, parasitic motion and every joint for a pose.
    Ik {
        #[command(flatten)]
        pose: PoseArgs,
        #[command(flatten)]
        common: CommonArgs,
    },
    /// Forward kinematics: the pose that leg lengths give.
    Fk {
        /// Leg lengths L1,L2,L3 in mm.
        #[arg(long, value_delimiter = ',', required = true)]
        legs_mm: Vec<f64>,
        #[command(flatten)]
        common: CommonArgs,
    },
    /// Post-process a CL file (seed Fig. 7.10) into joint commands.
    Cl {
        file: PathBuf,
        /// Clearance of approach/retract points along the tool axis, mm.
        #[arg(long, default_value_t = 10.0)]
        clearance_mm: f64,
        #[command(flatten)]
        common: CommonArgs,
    },
    /// Print the URDF of the seed's geometry (the source of urdf/hybrid_pkm.urdf).
    Urdf,
    /// Calibrate from measured poses: response surface (seed ch. 6) or geometric (LM).
    Calibrate {
        /// Measurement CSV (see README: commanded legs, measured tool tip and axis).
        #[arg(long)]
        measurements: PathBuf,
        /// rsm (the seed's response surfaces) or geometric (error-model identification).
        #[arg(long, default_value = "geometric")]
        method: calib::Method,
        /// Where to write the calibration.
        #[arg(long)]
        out: PathBuf,
        #[arg(long)]
        urdf: Option<PathBuf>,
        #[arg(long)]
        json: bool,
    },
    /// Simulate an imperfect machine and write its measurements (for studies and tests).
    Simulate {
        /// Random seed of the machine's errors and of the noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Number of measured poses.
        #[arg(long, default_value_t = 20)]
        poses: usize,
        /// Error magnitude of lengths (mm) and, in degrees, of angles.
        #[arg(long, default_value_t = 0.5)]
        error: f64,
        /// Measurement noise: tip (µm, σ) and axis (arc seconds, σ).
        #[arg(long, default_value_t = 1.0)]
        noise_um: f64,
        #[arg(long, default_value_t = 1.0)]
        noise_arcsec: f64,
        /// Where to measure: `plan` (D-optimal for identification over the work range),
        /// `rsm` (D-optimal for the response surface in the seed-like region), `random`.
        #[arg(long, default_value = "plan")]
        design: String,
        /// Where to write the measurements CSV.
        #[arg(long)]
        out: PathBuf,
        /// Also write the true machine (its parameters) as JSON, for checking a calibration.
        #[arg(long)]
        truth: Option<PathBuf>,
    },
}

#[derive(clap::Args, Debug)]
pub struct PoseArgs {
    /// Output-point height Z, mm (with θ1/θ2 or roll/pitch).
    #[arg(long, allow_negative_numbers = true)]
    z: Option<f64>,
    #[arg(long, allow_negative_numbers = true)]
    theta1_deg: Option<f64>,
    #[arg(long, allow_negative_numbers = true)]
    theta2_deg: Option<f64>,
    #[arg(long, allow_negative_numbers = true, conflicts_with_all = ["theta1_deg", "theta2_deg"])]
    roll_deg: Option<f64>,
    #[arg(long, allow_negative_numbers = true, conflicts_with_all = ["theta1_deg", "theta2_deg"])]
    pitch_deg: Option<f64>,
    /// Tool tip x,y,z in the workpiece frame, mm (with --axis instead of a pose).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true, conflicts_with_all = ["z", "theta1_deg", "theta2_deg", "roll_deg", "pitch_deg"])]
    tip_mm: Option<Vec<f64>>,
    /// Tool axis x,y,z, unit, pointing spindle-ward (default 0,0,1).
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        requires = "tip_mm"
    )]
    axis: Option<Vec<f64>>,
}

#[derive(clap::Args, Debug)]
pub struct CommonArgs {
    /// URDF of the mechanism (default: the built-in urdf/hybrid_pkm.urdf).
    #[arg(long)]
    urdf: Option<PathBuf>,
    /// A calibration (from `mechanism calibrate`) to correct the legs with.
    #[arg(long)]
    calibration: Option<PathBuf>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
    /// Record /mechanism/joint_states and /robot_description to this MCAP bag.
    #[arg(long)]
    bag: Option<PathBuf>,
}

fn load_urdf(path: &Option<PathBuf>) -> anyhow::Result<(String, UrdfTree, Geometry)> {
    let (text, name) = match path {
        Some(p) => (read_text(p)?, p.display().to_string()),
        None => (
            mechanism_kin::BUILTIN_URDF.to_string(),
            "built-in URDF".into(),
        ),
    };
    let (tree, geom) = mechanism_kin::urdf::load(&text).map_err(|e| anyhow!("{name}: {e}"))?;
    Ok((text, tree, geom))
}

fn load_calibration(path: &Option<PathBuf>) -> anyhow::Result<Option<Calibration>> {
    path.as_ref()
        .map(|p| {
            let text = read_text(p)?;
            Calibration::from_json(&text).map_err(|e| anyhow!("{}: {e}", p.display()))
        })
        .transpose()
}

/// A bag of joint states (and the tool poses they answer) with the URDF. A program has no
/// wall-clock time: stamps count 10 ms per command from 0, so the bag is reproducible.
struct JointBag {
    writer: BagWriter<BufWriter<File>>,
    states: cell_bag::ChannelId,
    poses: cell_bag::ChannelId,
    stamp_ns: u64,
}

impl JointBag {
    fn create(path: &Path, urdf: &str) -> anyhow::Result<Self> {
        let file =
            File::create(path).with_context(|| format!("creating bag {}", path.display()))?;
        let mut writer = BagWriter::new(BufWriter::new(file), &WriterOptions::default())?;
        let description = writer.add_topic(
            "/robot_description",
            StringMsg::TYPE,
            QosRecord {
                durability: cell_bag::Durability::TransientLocal,
                depth: 1,
                ..QosRecord::ROS_DEFAULT
            },
        )?;
        let states = writer.add_topic(
            "/mechanism/joint_states",
            JointState::TYPE,
            QosRecord::ROS_DEFAULT,
        )?;
        let poses = writer.add_topic(
            "/mechanism/tool_pose",
            PoseStamped::TYPE,
            QosRecord::ROS_DEFAULT,
        )?;
        let stamp_ns = 0;
        writer.write_message(
            description,
            stamp_ns,
            &StringMsg {
                data: urdf.to_string(),
            },
        )?;
        Ok(JointBag {
            writer,
            states,
            poses,
            stamp_ns,
        })
    }

    /// One tool pose and its joint state per command, 10 ms apart on the bag's clock.
    fn push(&mut self, target: &ToolTarget, values: &[f64]) -> anyhow::Result<()> {
        self.stamp_ns += 10_000_000;
        let stamp = Time::from_nanos(self.stamp_ns as i64);
        self.writer.write_message(
            self.poses,
            self.stamp_ns,
            &mechanism_kin::node::pose_message(target, stamp),
        )?;
        self.push_state(values)
    }

    /// Like [`JointBag::push`], the joint state solved for the pose exactly as the message
    /// carries it (metres and a quaternion), as the node would solve it: replaying the bag's
    /// poses into the node gives these states bit for bit.
    fn push_solved(
        &mut self,
        target: &ToolTarget,
        geom: &Geometry,
        tree: &UrdfTree,
        fk: &mut ForwardSolver,
    ) -> anyhow::Result<()> {
        let message = mechanism_kin::node::pose_message(target, Time::from_nanos(0));
        let as_sent = mechanism_kin::node::target_from_pose(&message);
        let e = evaluate(geom, tree, fk, &as_sent)?;
        self.push(target, &e.joint_values_si)
    }

    fn push_state(&mut self, values: &[f64]) -> anyhow::Result<()> {
        let msg = JointState {
            header: Header {
                stamp: Time::from_nanos(self.stamp_ns as i64),
                frame_id: String::new(),
            },
            name: joint_names(),
            position: values.to_vec(),
            velocity: vec![],
            effort: vec![],
        };
        self.writer
            .write_message(self.states, self.stamp_ns, &msg)?;
        Ok(())
    }

    fn finish(self) -> anyhow::Result<()> {
        let (mut sink, _) = self.writer.finish()?;
        std::io::Write::flush(&mut sink)?;
        Ok(())
    }
}

fn evaluation_json(e: &Evaluation) -> serde_json::Value {
    let ik = &e.solution.ik;
    let (t1, t2) = ik.pose.tilt.theta();
    let (roll, pitch) = ik.pose.tilt.roll_pitch();
    json!({
        "leg_lengths_mm": ik.legs_mm,
        "table_mm": e.solution.table_mm,
        "pose": {
            "z_mm": ik.pose.z_mm,
            "theta1_deg": t1.to_degrees(),
            "theta2_deg": t2.to_degrees(),
            "roll_deg": roll.to_degrees(),
            "pitch_deg": pitch.to_degrees(),
            "parasitic_yaw_deg": mechanism_kin::Tilt::parasitic_yaw(roll, pitch).to_degrees(),
        },
        "parasitic_xy_mm": ik.parasitic_xy_mm,
        "joints": joint_names().iter().zip(&e.joint_values_si).map(|(n, v)| (n.clone(), json!(v))).collect::<serde_json::Map<_, _>>(),
        "checks": {
            "fk_residual_mm": e.fk_residual_mm,
            "fk_iterations": e.fk_iterations,
            "loop_closure_residual_m": e.loop_closure_residual_m,
            "io_ratio": e.io_ratio,
            "leg_margin_mm": e.leg_margin_mm,
            "swing_margin_deg": e.swing_margin_rad.to_degrees(),
            "table_margin_mm": e.table_margin_mm,
        }
    })
}

fn three(what: &str, v: &[f64]) -> anyhow::Result<[f64; 3]> {
    match v {
        [a, b, c] => Ok([*a, *b, *c]),
        _ => bail!(
            "{what} needs three comma-separated numbers, got {}",
            v.len()
        ),
    }
}

/// A text input (CL, measurements, URDF, calibration): a file that is not UTF-8 text is refused
/// naming the line and column of its first bad byte.
fn read_text(path: &Path) -> anyhow::Result<String> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    String::from_utf8(bytes).map_err(|e| {
        let good = &e.as_bytes()[..e.utf8_error().valid_up_to()];
        let line = good.iter().filter(|&&b| b == b'\n').count() + 1;
        let column = good.len() - good.iter().rposition(|&b| b == b'\n').map_or(0, |i| i + 1) + 1;
        anyhow!(
            "{}:{line}:{column}: byte 0x{:02x} is not UTF-8 text (is this a binary file?)",
            path.display(),
            e.as_bytes()[good.len()]
        )
    })
}

fn pose_target(args: &PoseArgs, geom: &Geometry) -> anyhow::Result<ToolTarget> {
    if let Some(tip) = &args.tip_mm {
        let tip = three("--tip-mm", tip)?;
        let axis = three("--axis", &args.axis.clone().unwrap_or(vec![0.0, 0.0, 1.0]))?;
        let axis = Vector3::new(axis[0], axis[1], axis[2]);
        return Ok(ToolTarget {
            tip_mm: Vector3::new(tip[0], tip[1], tip[2]),
            axis,
        });
    }
    let z = args.z.ok_or_else(|| {
        anyhow!("give --z with --theta1-deg/--theta2-deg or --roll-deg/--pitch-deg, or --tip-mm")
    })?;
    // Each input named by its own flag (a NaN would otherwise surface as a derived quantity).
    for (flag, value) in [
        ("--z", Some(z)),
        ("--theta1-deg", args.theta1_deg),
        ("--theta2-deg", args.theta2_deg),
        ("--roll-deg", args.roll_deg),
        ("--pitch-deg", args.pitch_deg),
    ] {
        if let Some(v) = value.filter(|v| !v.is_finite()) {
            bail!("{flag} is {v}: give a finite number");
        }
    }
    let pose = match (
        args.theta1_deg,
        args.theta2_deg,
        args.roll_deg,
        args.pitch_deg,
    ) {
        (t1, t2, None, None) => Pose::from_theta(
            z,
            t1.unwrap_or(0.0).to_radians(),
            t2.unwrap_or(0.0).to_radians(),
        ),
        (None, None, r, p) => Pose::from_roll_pitch(
            z,
            r.unwrap_or(0.0).to_radians(),
            p.unwrap_or(0.0).to_radians(),
        ),
        _ => bail!("give either θ1/θ2 or roll/pitch"),
    };
    // A platform pose: the tool tip it reaches with the table at the position that puts the
    // workpiece origin under the tool (table = tip's x, y).
    let normal = pose.tilt.normal();
    Ok(ToolTarget {
        tip_mm: Vector3::new(0.0, 0.0, pose.z_mm - geom.tool_length_mm * normal.z),
        axis: normal,
    })
}

pub fn run(command: MechanismCommand) -> anyhow::Result<()> {
    match command {
        MechanismCommand::Urdf => {
            print!("{}", mechanism_kin::urdf::write(&Geometry::default()));
            Ok(())
        }
        MechanismCommand::Ik { pose, common } => {
            let (text, tree, geom) = load_urdf(&common.urdf)?;
            let calibration = load_calibration(&common.calibration)?;
            let target = pose_target(&pose, &geom)?;
            let mut fk = ForwardSolver::default();
            let e = evaluate(&geom, &tree, &mut fk, &target)?;
            let corrected = calibration
                .as_ref()
                .map(|c| c.corrected_inverse(&geom, &target))
                .transpose()?;
            if let Some(bag) = &common.bag {
                let mut b = JointBag::create(bag, &text)?;
                b.push_solved(&target, &geom, &tree, &mut fk)?;
                b.finish()?;
            }
            if common.json {
                let mut v = evaluation_json(&e);
                if let Some(c) = &corrected {
                    v["calibrated"] = c.to_json();
                }
                println!("{}", serde_json::to_string_pretty(&v)?);
            } else {
                let ik = &e.solution.ik;
                let (t1, t2) = ik.pose.tilt.theta();
                println!(
                    "pose       Z {:.6} mm  θ1 {:.6}°  θ2 {:.6}°",
                    ik.pose.z_mm,
                    t1.to_degrees(),
                    t2.to_degrees()
                );
                println!(
                    "legs       L1 {:.6}  L2 {:.6}  L3 {:.6} mm",
                    ik.legs_mm[0], ik.legs_mm[1], ik.legs_mm[2]
                );
                println!(
                    "parasitic  X_u {:.6}  Y_u {:.6} mm",
                    ik.parasitic_xy_mm[0], ik.parasitic_xy_mm[1]
                );
                println!(
                    "table      X {:.6}  Y {:.6} mm",
                    e.solution.table_mm[0], e.solution.table_mm[1]
                );
                println!(
                    "checks     FK residual {:.2e} mm ({} iterations), loop closure {:.2e} m, io ratio {:.6}",
                    e.fk_residual_mm, e.fk_iterations, e.loop_closure_residual_m, e.io_ratio
                );
                if let Some(c) = &corrected {
                    println!("calibrated {}", c.to_json());
                }
            }
            Ok(())
        }
        MechanismCommand::Fk { legs_mm, common } => {
            let (text, _tree, geom) = load_urdf(&common.urdf)?;
            let calibration = load_calibration(&common.calibration)?;
            let legs = three("--legs-mm", &legs_mm)?;
            let mut fk = ForwardSolver::default();
            let sol = fk.solve(&geom, legs)?;
            let ik = geom.inverse_unchecked(&sol.pose);
            let (t1, t2) = sol.pose.tilt.theta();
            let (roll, pitch) = sol.pose.tilt.roll_pitch();
            let tip = geom.tool_tip_mm(&ik);
            let predicted = calibration
                .as_ref()
                .map(|c| c.predicted_tool(&geom, legs))
                .transpose()?;
            if let Some(bag) = &common.bag {
                let joints = geom.joint_positions(&ik, [0.0, 0.0]);
                let mut b = JointBag::create(bag, &text)?;
                let reached = ToolTarget {
                    tip_mm: tip,
                    axis: sol.rotation.column(2).into_owned(),
                };
                b.push(&reached, &mechanism_kin::urdf::joint_values_si(&joints))?;
                b.finish()?;
            }
            let v = json!({
                "pose": {
                    "z_mm": sol.pose.z_mm,
                    "theta1_deg": t1.to_degrees(),
                    "theta2_deg": t2.to_degrees(),
                    "roll_deg": roll.to_degrees(),
                    "pitch_deg": pitch.to_degrees(),
                },
                "output_point_mm": [sol.output_point_mm.x, sol.output_point_mm.y, sol.output_point_mm.z],
                "tool_tip_mm": [tip.x, tip.y, tip.z],
                "tool_axis": [sol.rotation[(0, 2)], sol.rotation[(1, 2)], sol.rotation[(2, 2)]],
                "iterations": sol.iterations,
                "side_residual_mm": sol.side_residual_mm(&geom),
                "closure_residual_mm": sol.closure_residual_mm(&geom),
                "calibrated_tool": predicted.map(|(t, a)| json!({"tip_mm": [t.x, t.y, t.z], "axis": [a.x, a.y, a.z]})),
            });
            if common.json {
                println!("{}", serde_json::to_string_pretty(&v)?);
            } else {
                println!(
                    "pose   Z {:.9} mm  θ1 {:.9}°  θ2 {:.9}°  ({} iterations)",
                    sol.pose.z_mm,
                    t1.to_degrees(),
                    t2.to_degrees(),
                    sol.iterations
                );
                println!(
                    "point  P ({:.9}, {:.9}, {:.9}) mm, tool tip ({:.9}, {:.9}, {:.9}) mm",
                    sol.output_point_mm.x,
                    sol.output_point_mm.y,
                    sol.output_point_mm.z,
                    tip.x,
                    tip.y,
                    tip.z
                );
            }
            Ok(())
        }
        MechanismCommand::Cl {
            file,
            clearance_mm,
            common,
        } => {
            let (text, tree, geom) = load_urdf(&common.urdf)?;
            let calibration = load_calibration(&common.calibration)?;
            let name = file.display().to_string();
            let cl_text = read_text(&file)?;
            let opts = PostOptions {
                clearance_mm,
                ..PostOptions::default()
            };
            let points = cl::parse(&name, &cl_text, &opts)?;
            let commands = cl::post_process(&name, &geom, &points, &opts)?;
            let mut bag = common
                .bag
                .as_ref()
                .map(|b| JointBag::create(b, &text))
                .transpose()?;
            let mut fk = ForwardSolver::default();
            let mut rows = Vec::with_capacity(commands.len());
            let mut worst_fk: f64 = 0.0;
            let mut worst_loop: f64 = 0.0;
            for c in &commands {
                let e = mechanism_kin::report::check(&geom, &tree, &mut fk, &c.target, c.solution)
                    .map_err(|err| anyhow!("{name}:{}: {err}", c.line))?;
                worst_fk = worst_fk.max(e.fk_residual_mm);
                worst_loop = worst_loop.max(e.loop_closure_residual_m);
                // With a calibration, its command whole: the legs and the table that absorbs
                // the machine's X/Y error (the nominal table with corrected legs left the tip
                // off by that error).
                let (legs, table) = match &calibration {
                    Some(cal) => {
                        let corrected = cal
                            .corrected_inverse(&geom, &c.target)
                            .map_err(|err| anyhow!("{name}:{}: {err}", c.line))?;
                        (corrected.legs_mm, corrected.table_mm)
                    }
                    None => (e.solution.ik.legs_mm, e.solution.table_mm),
                };
                if let Some(b) = bag.as_mut() {
                    b.push_solved(&c.target, &geom, &tree, &mut fk)?;
                }
                rows.push(json!({
                    "line": c.line,
                    "kind": c.kind,
                    "tip_mm": [c.target.tip_mm.x, c.target.tip_mm.y, c.target.tip_mm.z],
                    "axis": [c.target.axis.x, c.target.axis.y, c.target.axis.z],
                    "leg_lengths_mm": legs,
                    "table_mm": table,
                }));
            }
            if let Some(b) = bag {
                b.finish()?;
            }
            let count = |k: MoveKind| commands.iter().filter(|c| c.kind == k).count();
            if common.json {
                println!(
                    "{}",
                    serde_json::to_string_pretty(&json!({
                        "commands": rows,
                        "paths": count(MoveKind::Approach),
                        "max_fk_residual_mm": worst_fk,
                        "max_loop_closure_residual_m": worst_loop,
                    }))?
                );
            } else {
                println!(
                    "{name}: {} CL points, {} paths → {} joint commands ({} approach, {} work, {} retract); FK check ≤ {:.2e} mm, loop closure ≤ {:.2e} m",
                    points.len(),
                    count(MoveKind::Approach),
                    commands.len(),
                    count(MoveKind::Approach),
                    count(MoveKind::Work),
                    count(MoveKind::Retract),
                    worst_fk,
                    worst_loop
                );
            }
            Ok(())
        }
        MechanismCommand::Calibrate {
            measurements,
            method,
            out,
            urdf,
            json,
        } => {
            let (_, _, geom) = load_urdf(&urdf)?;
            let name = measurements.display().to_string();
            let text = read_text(&measurements)?;
            let data = calib::measurements::parse(&name, &text)?;
            let cal = calib::calibrate(&geom, &data, method)?;
            std::fs::write(&out, cal.to_file_json())
                .with_context(|| format!("writing {}", out.display()))?;
            let summary = cal.summary();
            if json {
                println!("{}", serde_json::to_string_pretty(&summary)?);
            } else {
                println!("{}", serde_json::to_string_pretty(&summary)?);
                println!("wrote {}", out.display());
            }
            Ok(())
        }
        MechanismCommand::Simulate {
            seed,
            poses,
            error,
            noise_um,
            noise_arcsec,
            design,
            out,
            truth,
        } => {
            let geom = Geometry::default();
            let mut sim = calib::simulate::Simulation::new(
                &geom,
                seed,
                error,
                error.to_radians(),
                noise_um * 1e-3,
                (noise_arcsec / 3600.0).to_radians(),
            )?;
            let data = match design.as_str() {
                "plan" => sim.measure_legs(&calib::geometric::measurement_plan(
                    &geom,
                    poses,
                    &calib::geometric::IdentifyOptions::default(),
                )?)?,
                "rsm" => sim.measure_legs(
                    &calib::rsm::d_optimal_design(&geom, &calib::rsm::Region::default(), poses)?.0,
                )?,
                "random" => sim.measure(&geom, poses)?,
                other => bail!("--design `{other}`: expected plan, rsm or random"),
            };
            std::fs::write(&out, calib::measurements::to_csv(&data))
                .with_context(|| format!("writing {}", out.display()))?;
            if let Some(t) = truth {
                std::fs::write(&t, sim.truth_json())
                    .with_context(|| format!("writing {}", t.display()))?;
            }
            println!("wrote {} measured poses to {}", data.len(), out.display());
            Ok(())
        }
    }
}
