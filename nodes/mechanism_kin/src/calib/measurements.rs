//! The measurement CSV: one measured pose per line.
//!
//! ```text
//! l1_mm,l2_mm,l3_mm,tip_x_mm,tip_y_mm,tip_z_mm,axis_x,axis_y,axis_z
//! 391.204,402.117,377.950,1.0213,-0.4410,287.3321,0.0871,-0.0433,0.9952
//! ```
//!
//! `l*_mm` are the commanded leg lengths; `tip_*_mm` the measured tool tip in the base frame
//! (table at zero, e.g. by a laser tracker registered to the base); `axis_*` the measured unit
//! tool axis pointing from the tip to the spindle. Blank lines and `#` comments are allowed;
//! the header is required so that columns cannot be swapped silently.

use nalgebra::Vector3;

use super::CalibError;

/// One measured pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measurement {
    pub line: usize,
    pub legs_mm: [f64; 3],
    pub tip_mm: Vector3<f64>,
    pub axis: Vector3<f64>,
}

pub const HEADER: &str = "l1_mm,l2_mm,l3_mm,tip_x_mm,tip_y_mm,tip_z_mm,axis_x,axis_y,axis_z";

/// Parse a measurement file, naming file and line in every error.
pub fn parse(file: &str, text: &str) -> Result<Vec<Measurement>, CalibError> {
    let bad = |line: usize, reason: String| CalibError::Malformed {
        file: file.to_string(),
        line,
        reason,
    };
    let mut out = Vec::new();
    let mut header_seen = false;
    let columns: Vec<&str> = HEADER.split(',').collect();
    for (index, raw) in text.lines().enumerate() {
        let line = index + 1;
        let t = raw.trim();
        if t.is_empty() || t.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = t.split(',').map(str::trim).collect();
        if !header_seen {
            if fields != columns {
                return Err(bad(
                    line,
                    format!("first line must be the header `{HEADER}`"),
                ));
            }
            header_seen = true;
            continue;
        }
        if fields.len() != columns.len() {
            return Err(bad(
                line,
                format!("expected {} fields, found {}", columns.len(), fields.len()),
            ));
        }
        let mut v = [0.0; 9];
        for (k, f) in fields.iter().enumerate() {
            v[k] = f
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| bad(line, format!("{} `{f}` is not a finite number", columns[k])))?;
        }
        for k in 0..3 {
            if v[k] <= 0.0 {
                return Err(bad(
                    line,
                    format!("{} {} is not a positive leg length", columns[k], v[k]),
                ));
            }
        }
        let axis = Vector3::new(v[6], v[7], v[8]);
        let norm = axis.norm();
        if (norm - 1.0).abs() > 1e-6 || axis.z <= 0.0 {
            return Err(bad(
                line,
                format!(
                    "tool axis must be a unit vector pointing up; |a| = {norm:.9}, a_z = {}",
                    v[8]
                ),
            ));
        }
        out.push(Measurement {
            line,
            legs_mm: [v[0], v[1], v[2]],
            tip_mm: Vector3::new(v[3], v[4], v[5]),
            axis: axis / norm,
        });
    }
    if !header_seen {
        return Err(bad(
            1,
            format!("empty file: expected the header `{HEADER}`"),
        ));
    }
    if out.is_empty() {
        return Err(bad(text.lines().count().max(1), "no measurements".into()));
    }
    Ok(out)
}

/// Write measurements in the same format (full precision).
pub fn to_csv(data: &[Measurement]) -> String {
    let mut s = format!("{HEADER}\n");
    for m in data {
        s.push_str(&format!(
            "{:?},{:?},{:?},{:?},{:?},{:?},{:?},{:?},{:?}\n",
            m.legs_mm[0],
            m.legs_mm[1],
            m.legs_mm[2],
            m.tip_mm.x,
            m.tip_mm.y,
            m.tip_mm.z,
            m.axis.x,
            m.axis.y,
            m.axis.z
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors() {
        let m = Measurement {
            line: 2,
            legs_mm: [390.1, 400.2, 380.3],
            tip_mm: Vector3::new(1.0, -2.0, 290.5),
            axis: Vector3::new(0.1, 0.0, 1.0).normalize(),
        };
        let text = to_csv(&[m]);
        assert_eq!(parse("m.csv", &text).unwrap(), vec![m]);
        let cases = [
            ("1,2,3\n", 1, "header"),
            (
                &*format!("{HEADER}\n1,2,3,4,5,6,0,0,1,9\n"),
                2,
                "expected 9 fields",
            ),
            (&*format!("{HEADER}\n1,2,x,4,5,6,0,0,1\n"), 2, "l3_mm `x`"),
            (&*format!("{HEADER}\n1,2,3,4,5,6,0,0,2\n"), 2, "unit vector"),
            (
                &*format!("{HEADER}\n-1,2,3,4,5,6,0,0,1\n"),
                2,
                "positive leg",
            ),
            (&*format!("{HEADER}\n"), 1, "no measurements"),
        ];
        for (text, line, says) in cases {
            match parse("m.csv", text).unwrap_err() {
                CalibError::Malformed {
                    line: l, reason, ..
                } => {
                    assert_eq!(l, line, "{text}");
                    assert!(reason.contains(says), "{reason}");
                }
                other => panic!("{other}"),
            }
        }
    }
}
