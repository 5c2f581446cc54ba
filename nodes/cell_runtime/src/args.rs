//! The ROS 2 command line (`--ros-args ... [--]`), parsed as rcl does.
//!
//! Supported: `-p/--param [node:]name:=value`, `--params-file FILE`, `-r/--remap
//! [node:]from:=to` (including `__ns`, `__node`/`__name`), `--log-level [name:=]LEVEL`,
//! `-e/--enclave`, and the logging switches (`--enable-/--disable-rosout-logs`,
//! `--enable-/--disable-stdout-logs`, `--disable-external-lib-logs`, `--log-config-file`).
//! Anything else inside `--ros-args` is an error; arguments outside are left for the program.

/// A failure to understand the ROS command line.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ArgsError {
    #[error("`{flag}` needs a value")]
    MissingValue { flag: String },
    #[error("`{flag} {value}`: expected `name:=value`")]
    ExpectedAssignment { flag: String, value: String },
    #[error("unknown ROS argument `{0}` (inside --ros-args)")]
    UnknownArgument(String),
    #[error("unexpected arguments {0:?}: parameters go after --ros-args -p name:=value")]
    Unexpected(Vec<String>),
}

/// One `-r` remapping, optionally restricted to one node.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Remap {
    pub node: Option<String>,
    pub from: String,
    pub to: String,
}

/// One `-p` parameter, optionally restricted to one node; the value is raw YAML text.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ParamOverride {
    pub node: Option<String>,
    pub name: String,
    pub value_yaml: String,
}

/// Everything found inside `--ros-args` sections.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RosArgs {
    pub params: Vec<ParamOverride>,
    pub params_files: Vec<String>,
    pub remaps: Vec<Remap>,
    pub log_level: Option<String>,
    pub enclave: Option<String>,
    pub rosout_logs: Option<bool>,
    pub stdout_logs: Option<bool>,
}

impl RosArgs {
    /// Split `argv` (without the program name) into ROS arguments and the program's own.
    pub fn parse<S: AsRef<str>>(argv: &[S]) -> Result<(RosArgs, Vec<String>), ArgsError> {
        let mut ros = RosArgs::default();
        let mut rest = Vec::new();
        let mut i = 0;
        let mut inside = false;
        while i < argv.len() {
            let arg = argv[i].as_ref();
            i += 1;
            if !inside {
                if arg == "--ros-args" {
                    inside = true;
                } else {
                    rest.push(arg.to_string());
                }
                continue;
            }
            let mut value = |flag: &str| -> Result<String, ArgsError> {
                let v =
                    argv.get(i)
                        .map(|s| s.as_ref().to_string())
                        .ok_or(ArgsError::MissingValue {
                            flag: flag.to_string(),
                        })?;
                i += 1;
                Ok(v)
            };
            match arg {
                "--" => inside = false,
                "--ros-args" => {}
                "-p" | "--param" => {
                    let v = value(arg)?;
                    let (node, name, value_yaml) = split_assignment(arg, &v)?;
                    ros.params.push(ParamOverride {
                        node,
                        name,
                        value_yaml,
                    });
                }
                "--params-file" => ros.params_files.push(value(arg)?),
                "-r" | "--remap" => {
                    let v = value(arg)?;
                    let (node, from, to) = split_assignment(arg, &v)?;
                    ros.remaps.push(Remap { node, from, to });
                }
                "--log-level" => ros.log_level = Some(value(arg)?),
                "-e" | "--enclave" => ros.enclave = Some(value(arg)?),
                "--log-config-file" => {
                    value(arg)?;
                }
                "--enable-rosout-logs" => ros.rosout_logs = Some(true),
                "--disable-rosout-logs" => ros.rosout_logs = Some(false),
                "--enable-stdout-logs" => ros.stdout_logs = Some(true),
                "--disable-stdout-logs" => ros.stdout_logs = Some(false),
                "--enable-external-lib-logs" | "--disable-external-lib-logs" => {}
                other => return Err(ArgsError::UnknownArgument(other.to_string())),
            }
        }
        Ok((ros, rest))
    }

    /// The node name after `__node`/`__name` remaps that apply to a node started as `default`.
    pub fn node_name(&self, default: &str) -> String {
        self.special_remap(default, &["__node", "__name"])
            .unwrap_or_else(|| default.to_string())
    }

    /// The namespace after an `__ns` remap (always absolute, no trailing slash except root),
    /// for the node named `default_node_name` after its `__node` remaps: rcl matches a
    /// node-prefixed `__ns` rule against the renamed node.
    pub fn namespace(&self, default_node_name: &str, default: &str) -> String {
        let ns = self
            .special_remap(default_node_name, &["__ns"])
            .unwrap_or_else(|| default.to_string());
        let ns = if ns.starts_with('/') {
            ns
        } else {
            format!("/{ns}")
        };
        let trimmed = ns.trim_end_matches('/');
        if trimmed.is_empty() {
            "/".to_string()
        } else {
            trimmed.to_string()
        }
    }

    /// The first rule that applies, in command-line order, as rcl takes it
    /// (`_rcl_remap_first_match`), like the topic remaps.
    fn special_remap(&self, node: &str, keys: &[&str]) -> Option<String> {
        self.remaps
            .iter()
            .find(|r| {
                keys.contains(&r.from.as_str()) && r.node.as_deref().is_none_or(|n| n == node)
            })
            .map(|r| r.to.clone())
    }
}

/// `[node:]name:=value` → (node, name, value).
fn split_assignment(flag: &str, text: &str) -> Result<(Option<String>, String, String), ArgsError> {
    let bad = || ArgsError::ExpectedAssignment {
        flag: flag.to_string(),
        value: text.to_string(),
    };
    let (lhs, rhs) = text.split_once(":=").ok_or_else(bad)?;
    if lhs.is_empty() {
        return Err(bad());
    }
    // A node prefix is `node:`; names themselves never contain `:`.
    let (node, name) = match lhs.split_once(':') {
        Some((node, name)) if !node.is_empty() && !name.is_empty() => {
            (Some(node.to_string()), name.to_string())
        }
        Some(_) => return Err(bad()),
        None => (None, lhs.to_string()),
    };
    Ok((node, name, rhs.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splits_ros_and_program_arguments() {
        let argv = [
            "file.gcode",
            "--ros-args",
            "-p",
            "window:=64",
            "--param",
            "streamer:rate:=2.5",
            "--params-file",
            "p.yaml",
            "-r",
            "__ns:=/cell",
            "-r",
            "streamer:__node:=feeder",
            "--remap",
            "/gcode/moves:=/m",
            "--log-level",
            "debug",
            "--",
            "--verbose",
        ];
        let (ros, rest) = RosArgs::parse(&argv).unwrap();
        assert_eq!(rest, ["file.gcode", "--verbose"]);
        assert_eq!(ros.params.len(), 2);
        assert_eq!(ros.params[1].node.as_deref(), Some("streamer"));
        assert_eq!(ros.params[1].name, "rate");
        assert_eq!(ros.params[1].value_yaml, "2.5");
        assert_eq!(ros.params_files, ["p.yaml"]);
        assert_eq!(ros.node_name("streamer"), "feeder");
        assert_eq!(ros.node_name("other"), "other");
        assert_eq!(ros.namespace("streamer", "/"), "/cell");
        assert_eq!(ros.remaps[2].from, "/gcode/moves");
        assert_eq!(ros.log_level.as_deref(), Some("debug"));
    }

    #[test]
    fn errors_name_the_argument() {
        assert_eq!(
            RosArgs::parse(&["--ros-args", "-p"]).unwrap_err(),
            ArgsError::MissingValue { flag: "-p".into() }
        );
        assert_eq!(
            RosArgs::parse(&["--ros-args", "-p", "novalue"])
                .unwrap_err()
                .to_string(),
            "`-p novalue`: expected `name:=value`"
        );
        assert_eq!(
            RosArgs::parse(&["--ros-args", "--bogus"]).unwrap_err(),
            ArgsError::UnknownArgument("--bogus".into())
        );
        assert!(RosArgs::parse(&["--ros-args", "-r", ":x:=y"]).is_err());
    }

    /// Of two rules for the same name, the first applies (rcl's first match).
    #[test]
    fn the_first_applicable_node_or_namespace_remap_wins() {
        let (ros, _) = RosArgs::parse(&[
            "--ros-args",
            "-r",
            "streamer:__node:=x",
            "-r",
            "__node:=y",
            "-r",
            "__ns:=/a",
            "-r",
            "__ns:=/b",
        ])
        .unwrap();
        assert_eq!(ros.node_name("streamer"), "x");
        assert_eq!(ros.node_name("planner"), "y");
        assert_eq!(ros.namespace("streamer", "/"), "/a");
    }

    /// A namespace rule for the node names it as renamed, as rcl applies it.
    #[test]
    fn a_node_s_namespace_rule_names_it_as_renamed() {
        let (ros, _) = RosArgs::parse(&[
            "--ros-args",
            "-r",
            "streamer:__node:=feeder",
            "-r",
            "feeder:__ns:=/cell",
        ])
        .unwrap();
        let name = ros.node_name("streamer");
        assert_eq!(
            (name.as_str(), ros.namespace(&name, "/").as_str()),
            ("feeder", "/cell")
        );
    }

    #[test]
    fn namespace_normalisation() {
        let (ros, _) = RosArgs::parse(&["--ros-args", "-r", "__ns:=cell/"]).unwrap();
        assert_eq!(ros.namespace("n", "/"), "/cell");
        let (ros, _) = RosArgs::parse(&["--ros-args", "-r", "__ns:=/"]).unwrap();
        assert_eq!(ros.namespace("n", "/x"), "/");
    }
}
