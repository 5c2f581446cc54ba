//! The dependency graph holds no archived crate the project has moved off.

/// `serde_yaml` (and its `unsafe-libyaml`) were archived in 2024; the parameter files and
/// bag metadata are read with `yaml_serde`, the YAML organization's maintained fork of it.
#[test]
fn no_archived_yaml_crate_in_the_lock_files() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    for lock in ["Cargo.lock", "tests/fuzz/Cargo.lock", "firmware/Cargo.lock"] {
        let text = std::fs::read_to_string(root.join(lock)).unwrap();
        for archived in ["serde_yaml", "unsafe-libyaml"] {
            assert!(
                !text.contains(&format!("name = \"{archived}\"")),
                "{lock} still pulls in {archived}"
            );
        }
        assert!(text.contains("[[package]]"), "{lock} is not a lock file");
    }
}
