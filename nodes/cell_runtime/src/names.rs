//! Topic name resolution and remapping, as rcl does it: relative names live in the node's
//! namespace, `~` is the node's private namespace, and a remap rule `from:=to` matches after
//! both sides are expanded.

use crate::args::Remap;

/// A topic name that cannot be a ROS name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("invalid topic name `{name}`: {reason}")]
pub struct NameError {
    pub name: String,
    pub reason: &'static str,
}

/// Expands and remaps topic names for one node.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NameResolver {
    pub node_name: String,
    pub namespace: String,
    remaps: Vec<(String, String)>,
}

impl NameResolver {
    /// Rules restricted to another node are dropped; `__`-special rules are not topic rules.
    pub fn new(node_name: &str, namespace: &str, remaps: &[Remap]) -> Result<Self, NameError> {
        let mut r = NameResolver {
            node_name: node_name.to_string(),
            namespace: namespace.to_string(),
            remaps: Vec::new(),
        };
        for rule in remaps {
            if rule.from.starts_with("__") || rule.node.as_deref().is_some_and(|n| n != node_name) {
                continue;
            }
            let from = r.expand(&rule.from)?;
            let to = r.expand(&rule.to)?;
            r.remaps.push((from, to));
        }
        Ok(r)
    }

    /// Fully qualified node name, e.g. `/cell/gcode_streamer`.
    pub fn fully_qualified_node_name(&self) -> String {
        if self.namespace == "/" {
            format!("/{}", self.node_name)
        } else {
            format!("{}/{}", self.namespace, self.node_name)
        }
    }

    /// Expand a name to absolute form without remapping.
    pub fn expand(&self, name: &str) -> Result<String, NameError> {
        let err = |reason| NameError {
            name: name.to_string(),
            reason,
        };
        if name.is_empty() {
            return Err(err("empty"));
        }
        let absolute = if let Some(rest) = name.strip_prefix('~') {
            if !(rest.is_empty() || rest.starts_with('/')) {
                // rcl: `~` stands alone or before `/` (`~status` would read `/ns/nodestatus`).
                return Err(err("`~` must be followed by `/`"));
            }
            format!("{}{}", self.fully_qualified_node_name(), rest)
        } else if name.starts_with('/') {
            name.to_string()
        } else if self.namespace == "/" {
            format!("/{name}")
        } else {
            format!("{}/{name}", self.namespace)
        };
        if absolute.len() > 1 && absolute.ends_with('/') {
            return Err(err("ends with `/`"));
        }
        if absolute.contains("//") {
            return Err(err("contains `//`"));
        }
        let valid = absolute.split('/').skip(1).all(|t| {
            !t.is_empty()
                && !t.starts_with(|c: char| c.is_ascii_digit())
                && t.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        });
        if !valid {
            return Err(err("tokens must be [A-Za-z_][A-Za-z0-9_]*"));
        }
        Ok(absolute)
    }

    /// The name a topic really has: expanded, then the first matching remap rule applied.
    pub fn resolve(&self, name: &str) -> Result<String, NameError> {
        let expanded = self.expand(name)?;
        Ok(self
            .remaps
            .iter()
            .find(|(from, _)| *from == expanded)
            .map(|(_, to)| to.clone())
            .unwrap_or(expanded))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn remap(node: Option<&str>, from: &str, to: &str) -> Remap {
        Remap {
            node: node.map(String::from),
            from: from.into(),
            to: to.into(),
        }
    }

    #[test]
    fn expansion_and_remapping() {
        let rules = [
            remap(None, "moves", "/other/moves"),
            remap(Some("someone_else"), "/joint_states", "/x"),
            remap(None, "__ns", "/cell"),
        ];
        let r = NameResolver::new("planner", "/cell", &rules).unwrap();
        assert_eq!(r.fully_qualified_node_name(), "/cell/planner");
        assert_eq!(r.resolve("moves").unwrap(), "/other/moves");
        assert_eq!(r.resolve("/cell/moves").unwrap(), "/other/moves");
        assert_eq!(r.resolve("/joint_states").unwrap(), "/joint_states");
        assert_eq!(r.resolve("~/status").unwrap(), "/cell/planner/status");
        assert_eq!(r.resolve("~").unwrap(), "/cell/planner");
        assert!(r.resolve("~status").is_err(), "not /cell/plannerstatus");
        let root = NameResolver::new("n", "/", &[]).unwrap();
        assert_eq!(root.resolve("a/b").unwrap(), "/a/b");
        assert!(root.resolve("a//b").is_err());
        assert!(root.resolve("1abc").is_err());
        assert!(root.resolve("a-b").is_err());
    }
}
