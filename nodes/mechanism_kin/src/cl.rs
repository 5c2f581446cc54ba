//! The CL-data post-processor (seed ch. 7.5–7.6, Fig. 7.10).
//!
//! A CL file is CSV `Px,Py,Pz,Vx,Vy,Vz,flag`: the tool tip on the workpiece (mm), the unit
//! tool vector V pointing from the spindle to the tip, and `s` (start of a path), `w` (work
//! point) or `e` (end). Paths are `s w* e`. Between paths the tool leaves along its own axis:
//! after `e` it retracts by the clearance, and before the next `s` it comes in from the
//! clearance point along that point's axis, so approach and retract never cut sideways.
//! Blank lines, `#` comments and a `Px,Py,Pz,Vx,Vy,Vz,flag` header are allowed.

use nalgebra::Vector3;

use crate::error::KinError;
use crate::geometry::Geometry;
use crate::kinematics::{ToolSolution, ToolTarget};

/// A malformed or unreachable CL file, naming the line.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ClError {
    #[error("{file}:{line}: {reason}")]
    Malformed {
        file: String,
        line: usize,
        reason: String,
    },
    #[error("{file}:{line}: unreachable: {source}")]
    Unreachable {
        file: String,
        line: usize,
        source: KinError,
    },
}

/// One CL point as read.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClPoint {
    pub line: usize,
    pub tip_mm: Vector3<f64>,
    /// V: unit vector from spindle to tip.
    pub tool_vector: Vector3<f64>,
    pub flag: ClFlag,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum ClFlag {
    Start,
    Work,
    End,
}

/// What a joint command does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MoveKind {
    /// From the clearance point down the tool axis onto a path's start.
    Approach,
    /// Along a path (the `s`, `w` and `e` points).
    Work,
    /// Up the tool axis from a path's end to the clearance point.
    Retract,
}

/// One joint command of the post-processed program.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointCommand {
    pub kind: MoveKind,
    /// CL line the command comes from.
    pub line: usize,
    pub target: ToolTarget,
    pub solution: ToolSolution,
}

/// Post-processor options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PostOptions {
    /// Distance of the clearance point from the surface along the tool axis, mm.
    pub clearance_mm: f64,
    /// Largest accepted deviation of |V| from 1.
    pub unit_tolerance: f64,
}

impl Default for PostOptions {
    fn default() -> Self {
        PostOptions {
            clearance_mm: 10.0,
            unit_tolerance: 1e-6,
        }
    }
}

/// Parse a CL file, checking fields, numbers, unit vectors and the `s w* e` grammar.
pub fn parse(file: &str, text: &str, opts: &PostOptions) -> Result<Vec<ClPoint>, ClError> {
    let bad = |line: usize, reason: String| ClError::Malformed {
        file: file.to_string(),
        line,
        reason,
    };
    let mut points = Vec::new();
    let mut in_path: Option<usize> = None;
    let mut seen_data = false;
    let mut last_line = 0;
    for (index, raw) in text.lines().enumerate() {
        let line = index + 1;
        last_line = line;
        let trimmed = raw.trim();
        if trimmed.is_empty() || trimmed.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = trimmed.split(',').map(str::trim).collect();
        if !seen_data && fields.first().is_some_and(|f| f.eq_ignore_ascii_case("px")) {
            let header = ["px", "py", "pz", "vx", "vy", "vz", "flag"];
            if fields.len() != 7
                || !fields
                    .iter()
                    .zip(header)
                    .all(|(f, h)| f.eq_ignore_ascii_case(h))
            {
                return Err(bad(
                    line,
                    format!("header must be `Px,Py,Pz,Vx,Vy,Vz,flag`, found `{trimmed}`"),
                ));
            }
            continue;
        }
        seen_data = true;
        if fields.len() != 7 {
            return Err(bad(
                line,
                format!(
                    "expected 7 comma-separated fields Px,Py,Pz,Vx,Vy,Vz,flag, found {}",
                    fields.len()
                ),
            ));
        }
        let mut v = [0.0; 6];
        for (k, name) in ["Px", "Py", "Pz", "Vx", "Vy", "Vz"].iter().enumerate() {
            v[k] = fields[k]
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| {
                    bad(
                        line,
                        format!("{name} `{}` is not a finite number", fields[k]),
                    )
                })?;
        }
        let tool_vector = Vector3::new(v[3], v[4], v[5]);
        let norm = tool_vector.norm();
        if (norm - 1.0).abs() > opts.unit_tolerance {
            return Err(bad(
                line,
                format!("tool vector (Vx, Vy, Vz) has length {norm:.9}, not 1"),
            ));
        }
        let flag = match fields[6] {
            "s" | "S" => ClFlag::Start,
            "w" | "W" => ClFlag::Work,
            "e" | "E" => ClFlag::End,
            other => {
                return Err(bad(
                    line,
                    format!("flag `{other}` is not s (start), w (work) or e (end)"),
                ))
            }
        };
        match (flag, in_path) {
            (ClFlag::Start, Some(start)) => {
                return Err(bad(
                    line,
                    format!("`s` inside the path started at line {start} (missing `e`)"),
                ))
            }
            (ClFlag::Work | ClFlag::End, None) => {
                return Err(bad(
                    line,
                    format!("`{}` outside a path (missing `s`)", fields[6]),
                ))
            }
            (ClFlag::Start, None) => in_path = Some(line),
            (ClFlag::End, Some(_)) => in_path = None,
            (ClFlag::Work, Some(_)) => {}
        }
        points.push(ClPoint {
            line,
            tip_mm: Vector3::new(v[0], v[1], v[2]),
            tool_vector: tool_vector / norm,
            flag,
        });
    }
    if let Some(start) = in_path {
        return Err(bad(
            last_line,
            format!("file ends inside the path started at line {start} (missing `e`)"),
        ));
    }
    if points.is_empty() {
        return Err(bad(last_line.max(1), "no CL points".into()));
    }
    Ok(points)
}

/// Turn CL points into joint commands with approach and retract along the tool axis.
pub fn post_process(
    file: &str,
    geom: &Geometry,
    points: &[ClPoint],
    opts: &PostOptions,
) -> Result<Vec<JointCommand>, ClError> {
    let mut out = Vec::with_capacity(points.len() + 2 * points.len() / 4);
    let solve = |line: usize, kind: MoveKind, tip: Vector3<f64>, axis: Vector3<f64>| {
        let target = ToolTarget { tip_mm: tip, axis };
        geom.inverse_tool(&target)
            .map(|solution| JointCommand {
                kind,
                line,
                target,
                solution,
            })
            .map_err(|source| ClError::Unreachable {
                file: file.to_string(),
                line,
                source,
            })
    };
    for p in points {
        // The spindle-ward axis is −V.
        let axis = -p.tool_vector;
        let clear = p.tip_mm + axis * opts.clearance_mm;
        if p.flag == ClFlag::Start {
            out.push(solve(p.line, MoveKind::Approach, clear, axis)?);
        }
        out.push(solve(p.line, MoveKind::Work, p.tip_mm, axis)?);
        if p.flag == ClFlag::End {
            out.push(solve(p.line, MoveKind::Retract, clear, axis)?);
        }
    }
    Ok(out)
}

/// One CL line: `s` for a path's first point, `e` for its last, `w` between.
fn push_row(out: &mut String, tip: Vector3<f64>, v: Vector3<f64>, first: bool, last: bool) {
    let flag = match (first, last) {
        (true, _) => 's',
        (_, true) => 'e',
        _ => 'w',
    };
    out.push_str(&format!(
        "{:.9},{:.9},{:.9},{:.12},{:.12},{:.12},{flag}\n",
        tip.x, tip.y, tip.z, v.x, v.y, v.z
    ));
}

/// A CL file for a concave hemisphere of `radius_mm` centred at (0, 0, `centre_z_mm`):
/// passes in planes x = const (pick feed apart), tool normal to the surface (the seed's
/// Fig. 7.12(a) part), limited to `max_tilt_rad` from vertical.
pub fn hemisphere(
    radius_mm: f64,
    centre_z_mm: f64,
    pick_feed_mm: f64,
    step_mm: f64,
    max_tilt_rad: f64,
) -> String {
    let mut s = String::from("Px,Py,Pz,Vx,Vy,Vz,flag\n");
    let reach = radius_mm * max_tilt_rad.sin();
    let passes = (2.0 * reach / pick_feed_mm).floor() as i64;
    for k in 0..=passes {
        let x = -reach + k as f64 * pick_feed_mm;
        let ring = (reach * reach - x * x).max(0.0).sqrt();
        let n = ((2.0 * ring / step_mm).ceil() as i64).max(1);
        for j in 0..=n {
            let y = -ring + 2.0 * ring * j as f64 / n as f64;
            // Point on the bowl below the centre; V points from the centre (spindle side)
            // out to the surface.
            let z = centre_z_mm - (radius_mm * radius_mm - x * x - y * y).sqrt();
            let v = Vector3::new(x, y, z - centre_z_mm) / radius_mm;
            push_row(&mut s, Vector3::new(x, y, z), v, j == 0, j == n);
        }
    }
    s
}

/// A CL file for a flat Archimedean spiral at height `z_mm` (the seed's Fig. 7.12(e)), the
/// tool tilted toward the centre by `tilt_rad`, in one path.
pub fn spiral(turns: f64, pitch_mm: f64, z_mm: f64, step_mm: f64, tilt_rad: f64) -> String {
    let mut s = String::from("Px,Py,Pz,Vx,Vy,Vz,flag\n");
    let total_angle = turns * std::f64::consts::TAU;
    let mut angle = 0.0;
    let mut first = true;
    loop {
        let r = pitch_mm * angle / std::f64::consts::TAU;
        let (sa, ca) = angle.sin_cos();
        let (x, y) = (r * ca, r * sa);
        // V from spindle to tip: down, leaning outward so the spindle sits toward the centre.
        let v = Vector3::new(tilt_rad.sin() * ca, tilt_rad.sin() * sa, -tilt_rad.cos());
        let last = angle >= total_angle;
        push_row(&mut s, Vector3::new(x, y, z_mm), v, first, last);
        if last {
            break;
        }
        first = false;
        // arc-length step: ds ≈ sqrt(r² + (pitch/2π)²) dθ
        let ds = (r * r + (pitch_mm / std::f64::consts::TAU).powi(2)).sqrt();
        angle = (angle + step_mm / ds).min(total_angle);
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::ForwardSolver;

    fn run(text: &str) -> Result<Vec<JointCommand>, ClError> {
        let opts = PostOptions::default();
        let g = Geometry::default();
        let pts = parse("part.cl", text, &opts)?;
        post_process("part.cl", &g, &pts, &opts)
    }

    /// Re-derive the tool tip of each command by FK of its legs plus the table.
    fn check_commands(cmds: &[JointCommand]) {
        let g = Geometry::default();
        let mut fk = ForwardSolver::default();
        for c in cmds {
            let sol = fk.solve(&g, c.solution.ik.legs_mm).unwrap();
            let tip_work = sol.tool_tip_mm(&g)
                - Vector3::new(c.solution.table_mm[0], c.solution.table_mm[1], 0.0);
            assert!(
                (tip_work - c.target.tip_mm).amax() < 1e-9,
                "line {}",
                c.line
            );
            assert!((sol.rotation.column(2) - c.target.axis).amax() < 1e-12);
        }
    }

    #[test]
    fn seed_fig_7_10_example_is_processed() {
        let text = "Px,Py,Pz,Vx,Vy,Vz,flag
15,-51,67,0,-0.34,-0.940425,s
15,-13.07336141,58.57079529,0,-0.087155743,-0.996194698,w
15,0,58,0,0,-1,w
15,13.07336141,58.57079529,0,0.087155743,-0.996194698,w
15,26.04722665,60.27883705,0,0.173648178,-0.984807753,w
15,38.82285677,63.11112606,0,0.258819045,-0.965925826,w
15,51.3030215,67.04610688,0,0.342020143,-0.939692621,e
";
        // The workpiece sits on the table; lift its frame so tips are in the work range.
        let lifted: String = text
            .lines()
            .map(|l| {
                let f: Vec<&str> = l.split(',').collect();
                if f[0] == "Px" {
                    return format!("{l}\n");
                }
                let z: f64 = f[2].parse().unwrap();
                format!(
                    "{},{},{},{},{},{},{}\n",
                    f[0],
                    f[1],
                    z + 150.0,
                    f[3],
                    f[4],
                    f[5],
                    f[6]
                )
            })
            .collect();
        let cmds = run(&lifted).unwrap();
        assert_eq!(cmds.len(), 7 + 2);
        assert_eq!(cmds[0].kind, MoveKind::Approach);
        assert_eq!(cmds[8].kind, MoveKind::Retract);
        // approach is 10 mm up the tool axis from the start
        let d = cmds[0].target.tip_mm - cmds[1].target.tip_mm;
        assert!((d - cmds[1].target.axis * 10.0).amax() < 1e-12);
        check_commands(&cmds);
    }

    #[test]
    fn generated_hemisphere_and_spiral_post_process_exactly() {
        let bowl = hemisphere(60.0, 320.0, 5.0, 2.0, 18f64.to_radians());
        let cmds = run(&bowl).unwrap();
        let paths = bowl.lines().filter(|l| l.ends_with(",s")).count();
        assert!(paths >= 5);
        assert_eq!(
            cmds.iter().filter(|c| c.kind == MoveKind::Approach).count(),
            paths
        );
        assert_eq!(
            cmds.iter().filter(|c| c.kind == MoveKind::Retract).count(),
            paths
        );
        check_commands(&cmds);
        // tool normal to the bowl: tip + R·(−V) is the centre
        for c in cmds.iter().filter(|c| c.kind == MoveKind::Work) {
            let centre = c.target.tip_mm + c.target.axis * 60.0;
            assert!((centre - Vector3::new(0.0, 0.0, 320.0)).amax() < 1e-6);
        }
        let sp = spiral(3.0, 8.0, 200.0, 2.0, 10f64.to_radians());
        let cmds = run(&sp).unwrap();
        assert_eq!(cmds.first().unwrap().kind, MoveKind::Approach);
        assert_eq!(cmds.last().unwrap().kind, MoveKind::Retract);
        check_commands(&cmds);
    }

    #[test]
    fn malformed_lines_are_named() {
        let cases = [
            ("1,2,3,0,0,-1,s\n1,2,3,0,0,-1\n", 2, "expected 7"),
            ("1,2,3,0,0,-1,s\n1,x,3,0,0,-1,e\n", 2, "Py `x`"),
            ("1,2,3,0,0,-0.5,s\n", 1, "length 0.5"),
            ("1,2,3,0,0,-1,w\n", 1, "outside a path"),
            (
                "1,2,3,0,0,-1,s\n1,2,3,0,0,-1,s\n",
                2,
                "inside the path started at line 1",
            ),
            ("1,2,3,0,0,-1,s\n\n", 2, "file ends inside"),
            ("1,2,3,0,0,-1,q\n", 1, "flag `q`"),
            ("Px,Py,Pz,Vx,Vy,flag\n", 1, "header"),
            ("1,2,inf,0,0,-1,s\n", 1, "Pz `inf`"),
        ];
        for (text, line, says) in cases {
            let err = run(text).unwrap_err();
            match &err {
                ClError::Malformed {
                    line: l,
                    reason,
                    file,
                } => {
                    assert_eq!(*l, line, "{text:?}: {err}");
                    assert!(reason.contains(says), "{text:?}: {err}");
                    assert_eq!(file, "part.cl");
                }
                other => panic!("{text:?}: {other}"),
            }
        }
        // reachable syntax, unreachable point: named too
        let err = run("0,0,900,0,0,-1,s\n0,0,900,0,0,-1,e\n").unwrap_err();
        assert!(matches!(err, ClError::Unreachable { line: 1, .. }), "{err}");
    }
}
