//! Typed, validated node parameters from defaults, `--params-file` YAML and `-p` overrides.
//!
//! Files use the ROS 2 layout: keys down to `ros__parameters` name the node (`/cell/name`, or
//! `cell:` → `name:` nested as rcl nests namespaces; a bare name is a node in `/`), and a
//! whole segment may be `*` (any one) or `**` (any number), as rclcpp matches them; maps
//! under `ros__parameters` become dotted names. Later sources win: defaults, then files in order, then `-p`.
//! An unknown parameter, a value of the wrong type, or one outside its range is an error that
//! names the parameter and where the value came from. An integer is accepted for a double
//! parameter (it loses nothing); nothing else is coerced.

use std::collections::BTreeMap;
use std::fmt;

use crate::args::ParamOverride;

/// A parameter value, with ROS 2's parameter types.
#[derive(Debug, Clone, PartialEq)]
pub enum ParamValue {
    Bool(bool),
    Integer(i64),
    Double(f64),
    String(String),
    BoolArray(Vec<bool>),
    IntegerArray(Vec<i64>),
    DoubleArray(Vec<f64>),
    StringArray(Vec<String>),
}

impl ParamValue {
    pub fn type_name(&self) -> &'static str {
        match self {
            ParamValue::Bool(_) => "bool",
            ParamValue::Integer(_) => "integer",
            ParamValue::Double(_) => "double",
            ParamValue::String(_) => "string",
            ParamValue::BoolArray(_) => "bool array",
            ParamValue::IntegerArray(_) => "integer array",
            ParamValue::DoubleArray(_) => "double array",
            ParamValue::StringArray(_) => "string array",
        }
    }
}

impl fmt::Display for ParamValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ParamValue::Bool(v) => write!(f, "{v}"),
            ParamValue::Integer(v) => write!(f, "{v}"),
            ParamValue::Double(v) => write!(f, "{v}"),
            ParamValue::String(v) => write!(f, "{v:?}"),
            ParamValue::BoolArray(v) => write!(f, "{v:?}"),
            ParamValue::IntegerArray(v) => write!(f, "{v:?}"),
            ParamValue::DoubleArray(v) => write!(f, "{v:?}"),
            ParamValue::StringArray(v) => write!(f, "{v:?}"),
        }
    }
}

/// A declared parameter: name, default (which fixes the type), meaning, and numeric range.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamSpec {
    pub name: &'static str,
    pub default: ParamValue,
    pub description: &'static str,
    /// Inclusive bounds for numeric parameters (each element of numeric arrays).
    pub range: Option<(f64, f64)>,
}

impl ParamSpec {
    pub const fn new(name: &'static str, default: ParamValue, description: &'static str) -> Self {
        ParamSpec {
            name,
            default,
            description,
            range: None,
        }
    }
    pub const fn range(mut self, min: f64, max: f64) -> Self {
        self.range = Some((min, max));
        self
    }
}

/// A parameter problem, naming the parameter and the source of the bad value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ParamError {
    #[error("{source_name}: unknown parameter `{name}` for node {node} (known: {known})")]
    Unknown {
        node: String,
        name: String,
        source_name: String,
        known: String,
    },
    #[error("{source_name}: parameter `{name}` is {expected}, got {given} `{value}`")]
    WrongType {
        name: String,
        expected: &'static str,
        given: &'static str,
        value: String,
        source_name: String,
    },
    #[error("{source_name}: parameter `{name}` = {value} is outside [{min}, {max}]")]
    OutOfRange {
        name: String,
        value: String,
        min: f64,
        max: f64,
        source_name: String,
    },
    #[error("parameter `{name}`: {problem}")]
    Invalid { name: String, problem: String },
    #[error("{source_name}: {message}")]
    BadYaml {
        source_name: String,
        message: String,
    },
}

/// The resolved parameters of one node.
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    values: BTreeMap<String, ParamValue>,
}

impl Params {
    /// Resolve `specs` for the node `fully_qualified_name` from `(file name, YAML text)` pairs
    /// and `-p` overrides.
    pub fn resolve(
        specs: &[ParamSpec],
        fully_qualified_name: &str,
        files: &[(String, String)],
        overrides: &[ParamOverride],
    ) -> Result<Params, ParamError> {
        let mut values: BTreeMap<String, ParamValue> = specs
            .iter()
            .map(|s| (s.name.to_string(), s.default.clone()))
            .collect();
        let base_name = fully_qualified_name.rsplit('/').next().unwrap_or_default();
        for (file, text) in files {
            let doc: yaml_serde::Value =
                yaml_serde::from_str(text).map_err(|e| ParamError::BadYaml {
                    source_name: file.clone(),
                    message: e.to_string(),
                })?;
            let Some(map) = doc.as_mapping() else {
                if doc.is_null() {
                    continue;
                }
                return Err(ParamError::BadYaml {
                    source_name: file.clone(),
                    message: "top level must be a map of node names".into(),
                });
            };
            let mut sections = Vec::new();
            node_sections("", map, &mut sections).map_err(|message| ParamError::BadYaml {
                source_name: file.clone(),
                message,
            })?;
            for (selector, params) in sections {
                if !selector_matches(&selector, fully_qualified_name) {
                    continue;
                }
                let mut flat = Vec::new();
                flatten("", params, &mut flat);
                for (name, value) in flat {
                    // A section for many nodes sets what each declares (rclcpp ignores an
                    // override no declaration takes); one for this node alone is checked.
                    let for_many = selector
                        .rsplit('/')
                        .next()
                        .is_some_and(|last| matches!(last, "*" | "**"));
                    if for_many && !specs.iter().any(|s| s.name == name) {
                        continue;
                    }
                    let source_name = format!("{file} [{selector}]");
                    set(
                        specs,
                        &mut values,
                        fully_qualified_name,
                        &name,
                        &value,
                        &source_name,
                    )?;
                }
            }
        }
        for o in overrides {
            if o.node.as_deref().is_some_and(|n| n != base_name) {
                continue;
            }
            let value: yaml_serde::Value = yaml_serde::from_str(&o.value_yaml)
                .unwrap_or_else(|_| yaml_serde::Value::String(o.value_yaml.clone()));
            set(
                specs,
                &mut values,
                fully_qualified_name,
                &o.name,
                &value,
                &format!("-p {}:={}", o.name, o.value_yaml),
            )?;
        }
        Ok(Params { values })
    }

    pub fn get(&self, name: &str) -> Option<&ParamValue> {
        self.values.get(name)
    }

    /// Every parameter and its value, in name order.
    pub fn iter(&self) -> impl Iterator<Item = (&String, &ParamValue)> {
        self.values.iter()
    }

    /// Typed access; the spec list guarantees the type, so a mismatch is a programming error
    /// reported as a default-free panic message naming the parameter.
    pub fn f64(&self, name: &str) -> f64 {
        match self.values.get(name) {
            Some(ParamValue::Double(v)) => *v,
            other => panic!("parameter {name} is not a declared double: {other:?}"),
        }
    }
    pub fn i64(&self, name: &str) -> i64 {
        match self.values.get(name) {
            Some(ParamValue::Integer(v)) => *v,
            other => panic!("parameter {name} is not a declared integer: {other:?}"),
        }
    }
    pub fn bool(&self, name: &str) -> bool {
        match self.values.get(name) {
            Some(ParamValue::Bool(v)) => *v,
            other => panic!("parameter {name} is not a declared bool: {other:?}"),
        }
    }
    pub fn string(&self, name: &str) -> &str {
        match self.values.get(name) {
            Some(ParamValue::String(v)) => v,
            other => panic!("parameter {name} is not a declared string: {other:?}"),
        }
    }
    pub fn strings(&self, name: &str) -> &[String] {
        match self.values.get(name) {
            Some(ParamValue::StringArray(v)) => v,
            other => panic!("parameter {name} is not a declared string array: {other:?}"),
        }
    }
    pub fn f64s(&self, name: &str) -> &[f64] {
        match self.values.get(name) {
            Some(ParamValue::DoubleArray(v)) => v,
            other => panic!("parameter {name} is not a declared double array: {other:?}"),
        }
    }

    /// A double array that must hold a position: exactly three finite values, `axes` naming
    /// them for the message (e.g. "bed rad, arm m, z m").
    pub fn finite3(&self, name: &str, axes: &str) -> Result<[f64; 3], ParamError> {
        match *self.f64s(name) {
            [a, b, c] if [a, b, c].iter().all(|v| v.is_finite()) => Ok([a, b, c]),
            ref other => Err(ParamError::Invalid {
                name: name.to_string(),
                problem: format!("needs 3 finite values ({axes}), got {other:?}"),
            }),
        }
    }

    /// A sampling period (s): 0 for none, else at least [`MIN_SAMPLE_PERIOD_S`]. A far
    /// shorter one would publish samples without end before anything else is done.
    pub fn sample_period_s(&self, name: &str) -> Result<f64, ParamError> {
        match self.f64(name) {
            period if period == 0.0 || period >= MIN_SAMPLE_PERIOD_S => Ok(period),
            period => Err(ParamError::Invalid {
                name: name.to_string(),
                problem: format!("is {period} s: 0 (none) or at least {MIN_SAMPLE_PERIOD_S} s"),
            }),
        }
    }
}

/// Shortest period of plan-time samples: a thousand a second of plan is far more than a
/// viewer draws.
pub const MIN_SAMPLE_PERIOD_S: f64 = 1e-3;

/// The node sections of a params file: the path of keys down to each `ros__parameters` map
/// (`/cell/streamer:` or `cell:` → `streamer:`, as rcl's parser nests namespaces), with it.
fn node_sections<'a>(
    prefix: &str,
    map: &'a yaml_serde::Mapping,
    out: &mut Vec<(String, &'a yaml_serde::Value)>,
) -> Result<(), String> {
    for (key, value) in map {
        let Some(key) = key.as_str() else {
            return Err(format!("`{prefix}`: a key that is not a name"));
        };
        if key == "ros__parameters" {
            out.push((prefix.to_string(), value));
            continue;
        }
        let path = format!("{prefix}/{}", key.trim_matches('/'));
        if let Some(bad) = path
            .split('/')
            .find(|segment| segment.contains('*') && !matches!(*segment, "*" | "**"))
        {
            // rcl refuses the file: `*` and `**` stand for whole segments only.
            return Err(format!(
                "`{path}`: `{bad}` is no node name (`*` and `**` stand alone)"
            ));
        }
        match value.as_mapping() {
            Some(inner) => node_sections(&path, inner, out)?,
            None => {
                let node = if prefix.is_empty() { "/" } else { prefix };
                return Err(format!(
                    "`{node}`: `{key}` is neither a node (a map) nor `ros__parameters`"
                ));
            }
        }
    }
    Ok(())
}

/// Whether the section `selector` (absolute, segments as rclcpp matches them: `**` any
/// number of segments, `*` any one) applies to the node `fqn`.
fn selector_matches(selector: &str, fqn: &str) -> bool {
    let pattern: Vec<&str> = selector.split('/').filter(|s| !s.is_empty()).collect();
    let name: Vec<&str> = fqn.split('/').filter(|s| !s.is_empty()).collect();
    segments_match(&pattern, &name)
}

fn segments_match(pattern: &[&str], name: &[&str]) -> bool {
    match pattern.split_first() {
        None => name.is_empty(),
        Some((&"**", rest)) => {
            segments_match(rest, name) || (!name.is_empty() && segments_match(pattern, &name[1..]))
        }
        Some((p, rest)) => name
            .split_first()
            .is_some_and(|(n, name_rest)| (*p == "*" || p == n) && segments_match(rest, name_rest)),
    }
}

fn flatten(prefix: &str, value: &yaml_serde::Value, out: &mut Vec<(String, yaml_serde::Value)>) {
    match value.as_mapping() {
        Some(map) => {
            for (k, v) in map {
                let key = k
                    .as_str()
                    .map(String::from)
                    .unwrap_or_else(|| format!("{k:?}"));
                let name = if prefix.is_empty() {
                    key
                } else {
                    format!("{prefix}.{key}")
                };
                flatten(&name, v, out);
            }
        }
        None => out.push((prefix.to_string(), value.clone())),
    }
}

fn set(
    specs: &[ParamSpec],
    values: &mut BTreeMap<String, ParamValue>,
    node: &str,
    name: &str,
    value: &yaml_serde::Value,
    source_name: &str,
) -> Result<(), ParamError> {
    // ROS tools set these on every node; they are not ours to reject.
    if name == "use_sim_time" || name.starts_with("qos_overrides.") {
        return Ok(());
    }
    let spec = specs
        .iter()
        .find(|s| s.name == name)
        .ok_or_else(|| ParamError::Unknown {
            node: node.to_string(),
            name: name.to_string(),
            source_name: source_name.to_string(),
            known: specs.iter().map(|s| s.name).collect::<Vec<_>>().join(", "),
        })?;
    let converted = convert(&spec.default, value).ok_or_else(|| ParamError::WrongType {
        name: name.to_string(),
        expected: spec.default.type_name(),
        given: yaml_type(value),
        value: yaml_serde::to_string(value)
            .unwrap_or_default()
            .trim()
            .to_string(),
        source_name: source_name.to_string(),
    })?;
    let numbers: Vec<f64> = match &converted {
        ParamValue::Integer(v) => vec![*v as f64],
        ParamValue::Double(v) => vec![*v],
        ParamValue::IntegerArray(v) => v.iter().map(|&x| x as f64).collect(),
        ParamValue::DoubleArray(v) => v.clone(),
        _ => vec![],
    };
    // NaN is no setting (and, unequal to itself, would fail the node's own check of its
    // declared values with a message about restarting).
    if numbers.iter().any(|x| x.is_nan()) {
        return Err(ParamError::Invalid {
            name: name.to_string(),
            problem: format!("{converted} holds NaN ({source_name})"),
        });
    }
    if let Some((min, max)) = spec.range {
        if numbers.iter().any(|x| !(min..=max).contains(x)) {
            return Err(ParamError::OutOfRange {
                name: name.to_string(),
                value: converted.to_string(),
                min,
                max,
                source_name: source_name.to_string(),
            });
        }
    }
    values.insert(name.to_string(), converted);
    Ok(())
}

fn yaml_type(v: &yaml_serde::Value) -> &'static str {
    match v {
        yaml_serde::Value::Null => "null",
        yaml_serde::Value::Bool(_) => "bool",
        yaml_serde::Value::Number(n) if n.is_f64() => "double",
        yaml_serde::Value::Number(_) => "integer",
        yaml_serde::Value::String(_) => "string",
        yaml_serde::Value::Sequence(_) => "array",
        yaml_serde::Value::Mapping(_) => "map",
        yaml_serde::Value::Tagged(_) => "tagged value",
    }
}

fn convert(like: &ParamValue, v: &yaml_serde::Value) -> Option<ParamValue> {
    use yaml_serde::Value as Y;
    let double = |v: &Y| match v {
        Y::Number(n) => n.as_f64(),
        _ => None,
    };
    let seq = |v: &Y| v.as_sequence().cloned();
    // rcl's YAML parser reads YAML 1.1's words for booleans too (`yes`, `off`, …).
    let boolean = |v: &Y| {
        v.as_bool().or_else(|| match v.as_str()? {
            "y" | "Y" | "yes" | "Yes" | "YES" | "on" | "On" | "ON" => Some(true),
            "n" | "N" | "no" | "No" | "NO" | "off" | "Off" | "OFF" => Some(false),
            _ => None,
        })
    };
    Some(match like {
        ParamValue::Bool(_) => ParamValue::Bool(boolean(v)?),
        ParamValue::Integer(_) => ParamValue::Integer(v.as_i64()?),
        ParamValue::Double(_) => ParamValue::Double(double(v)?),
        ParamValue::String(_) => ParamValue::String(v.as_str()?.to_string()),
        ParamValue::BoolArray(_) => {
            ParamValue::BoolArray(seq(v)?.iter().map(boolean).collect::<Option<_>>()?)
        }
        ParamValue::IntegerArray(_) => {
            ParamValue::IntegerArray(seq(v)?.iter().map(|x| x.as_i64()).collect::<Option<_>>()?)
        }
        ParamValue::DoubleArray(_) => {
            ParamValue::DoubleArray(seq(v)?.iter().map(double).collect::<Option<_>>()?)
        }
        ParamValue::StringArray(_) => ParamValue::StringArray(
            seq(v)?
                .iter()
                .map(|x| x.as_str().map(String::from))
                .collect::<Option<_>>()?,
        ),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn specs() -> Vec<ParamSpec> {
        vec![
            ParamSpec::new("window", ParamValue::Integer(64), "moves in flight").range(1.0, 1e6),
            ParamSpec::new("rate_hz", ParamValue::Double(10.0), "publish rate").range(0.0, 1000.0),
            ParamSpec::new("file", ParamValue::String(String::new()), "input"),
            ParamSpec::new("consumers", ParamValue::StringArray(vec![]), "who acks"),
            ParamSpec::new("limits.v", ParamValue::DoubleArray(vec![1.0]), "nested"),
        ]
    }

    #[test]
    fn a_sample_period_is_none_or_at_least_a_millisecond() {
        let period = |value: &str| {
            Params::resolve(&specs(), "/streamer", &[], &[o(None, "rate_hz", value)])
                .unwrap()
                .sample_period_s("rate_hz")
        };
        assert_eq!(period("0.0").unwrap(), 0.0);
        assert_eq!(period("0.001").unwrap(), 0.001);
        assert_eq!(period("2.5").unwrap(), 2.5);
        let error = period("0.0005").unwrap_err().to_string();
        assert!(
            error.contains("parameter `rate_hz`: is 0.0005 s: 0 (none) or at least 0.001 s"),
            "{error}"
        );
    }

    #[test]
    fn a_position_is_three_finite_values() {
        let at = |value: &str| {
            Params::resolve(&specs(), "/streamer", &[], &[o(None, "limits.v", value)])
                .unwrap()
                .finite3("limits.v", "x, y, z")
        };
        assert_eq!(at("[1.5, -2, 0.25]").unwrap(), [1.5, -2.0, 0.25]);
        for bad in ["[1.0, 2.0]", "[1.0, 2.0, 3.0, 4.0]", "[.inf, 0.0, 0.0]"] {
            let error = at(bad).expect_err(bad).to_string();
            assert!(
                error.contains("parameter `limits.v`: needs 3 finite values (x, y, z), got"),
                "{bad}: {error}"
            );
        }
    }

    /// Sections as rcl's parser and rclcpp's matching take them: namespaces nested as maps,
    /// `*` and `**` wildcards; a wildcard section sets only what the node declares.
    #[test]
    fn params_file_sections_nest_and_match_wildcards() {
        let window = |yaml: &str, node: &str| {
            let files = vec![("f.yaml".to_string(), yaml.to_string())];
            Params::resolve(&specs(), node, &files, &[]).map(|p| p.i64("window"))
        };
        let nested = "cell:\n  streamer:\n    ros__parameters:\n      window: 5\n";
        assert_eq!(window(nested, "/cell/streamer").unwrap(), 5);
        assert_eq!(
            window(nested, "/streamer").unwrap(),
            64,
            "another namespace"
        );
        let star = "/cell/*:\n  ros__parameters:\n    window: 6\n";
        assert_eq!(window(star, "/cell/streamer").unwrap(), 6);
        assert_eq!(
            window(star, "/cell/deep/streamer").unwrap(),
            64,
            "one segment only"
        );
        // rcl refuses the file: `*` is a whole segment or nothing.
        let partial = "/cell/stream*:\n  ros__parameters:\n    window: 7\n";
        assert!(matches!(
            window(partial, "/cell/streamer"),
            Err(ParamError::BadYaml { .. })
        ));
        let deep = "/**/streamer:\n  ros__parameters:\n    window: 8\n";
        assert_eq!(window(deep, "/streamer").unwrap(), 8);
        assert_eq!(window(deep, "/a/b/streamer").unwrap(), 8);
        // What only another node declares, set for all: not this node's business.
        let all = "/**:\n  ros__parameters:\n    window: 9\n    rate_of_another_node: 50\n";
        assert_eq!(window(all, "/x").unwrap(), 9);
        let exact = "/x:\n  ros__parameters:\n    rate_of_another_node: 50\n";
        assert!(matches!(
            window(exact, "/x"),
            Err(ParamError::Unknown { .. })
        ));
        // A section for one node wherever it is still catches a typo.
        let one = "/**/x:\n  ros__parameters:\n    windw: 5\n";
        assert!(matches!(
            window(one, "/a/x"),
            Err(ParamError::Unknown { .. })
        ));
    }

    #[test]
    fn booleans_read_as_rcl_reads_them() {
        let specs = vec![ParamSpec::new("on", ParamValue::Bool(false), "a switch")];
        for (text, value) in [
            ("true", true),
            ("yes", true),
            ("On", true),
            ("no", false),
            ("OFF", false),
        ] {
            let p = Params::resolve(&specs, "/n", &[], &[o(None, "on", text)]).unwrap();
            assert_eq!(p.bool("on"), value, "{text}");
        }
        assert!(Params::resolve(&specs, "/n", &[], &[o(None, "on", "maybe")]).is_err());
    }

    /// NaN is refused where it is set, naming it and where it came from: unequal to itself,
    /// it used to pass here and fail the node's start with a message about restarting.
    #[test]
    fn nan_is_no_setting() {
        for (name, value) in [("limits.v", "[1.0, .nan, 3.0]"), ("rate_hz", ".nan")] {
            let e = Params::resolve(&specs(), "/streamer", &[], &[o(None, name, value)])
                .unwrap_err()
                .to_string();
            assert!(
                e.contains(&format!("parameter `{name}`")) && e.contains("holds NaN (-p"),
                "{e}"
            );
        }
    }

    fn o(node: Option<&str>, name: &str, value: &str) -> ParamOverride {
        ParamOverride {
            node: node.map(String::from),
            name: name.into(),
            value_yaml: value.into(),
        }
    }

    #[test]
    fn files_then_overrides_with_selectors() {
        let yaml = "
/**:
  ros__parameters:
    rate_hz: 5
    use_sim_time: false
streamer:
  ros__parameters:
    window: 32
    limits:
      v: [1, 2.5]
/other:
  ros__parameters:
    window: 7
";
        let files = vec![("p.yaml".to_string(), yaml.to_string())];
        let p = Params::resolve(
            &specs(),
            "/streamer",
            &files,
            &[o(None, "file", "a b.gcode")],
        )
        .unwrap();
        assert_eq!(p.f64("rate_hz"), 5.0, "integer accepted for double");
        assert_eq!(p.i64("window"), 32);
        assert_eq!(p.f64s("limits.v"), [1.0, 2.5]);
        assert_eq!(p.string("file"), "a b.gcode");
        let p = Params::resolve(
            &specs(),
            "/streamer",
            &files,
            &[
                o(None, "window", "9"),
                o(Some("elsewhere"), "window", "11"),
                o(None, "consumers", "[/a, /b]"),
            ],
        )
        .unwrap();
        assert_eq!(p.i64("window"), 9);
        assert_eq!(p.strings("consumers"), ["/a", "/b"]);
        // `/**/name` selects by base name in any namespace.
        let files = vec![(
            "q.yaml".into(),
            "/**/streamer:\n  ros__parameters:\n    window: 3\n".into(),
        )];
        assert_eq!(
            Params::resolve(&specs(), "/ns/streamer", &files, &[])
                .unwrap()
                .i64("window"),
            3
        );
    }

    #[test]
    fn errors_name_parameter_and_source() {
        let e = Params::resolve(&specs(), "/s", &[], &[o(None, "windw", "3")]).unwrap_err();
        assert!(matches!(&e, ParamError::Unknown { name, .. } if name == "windw"));
        assert!(e.to_string().contains("-p windw:=3"), "{e}");
        let e = Params::resolve(&specs(), "/s", &[], &[o(None, "window", "2.5")]).unwrap_err();
        assert_eq!(
            e.to_string(),
            "-p window:=2.5: parameter `window` is integer, got double `2.5`"
        );
        let e = Params::resolve(&specs(), "/s", &[], &[o(None, "window", "0")]).unwrap_err();
        assert!(matches!(e, ParamError::OutOfRange { .. }), "{e}");
        let files = vec![("bad.yaml".into(), "s:\n  window: 3\n".into())];
        let e = Params::resolve(&specs(), "/s", &files, &[]).unwrap_err();
        assert!(e.to_string().contains("ros__parameters"), "{e}");
        let files = vec![("bad.yaml".into(), "s: [".into())];
        assert!(matches!(
            Params::resolve(&specs(), "/s", &files, &[]).unwrap_err(),
            ParamError::BadYaml { .. }
        ));
    }
}
