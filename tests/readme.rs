//! The README's topic table against the table the publishers use
//! (`cell_runtime::topics::SUITE_TOPICS`): a user reads the QoS to match from the README, so
//! the two must not drift apart (they had: `/polar/trajectory` was documented volatile at
//! depth 10,000 while its publisher offered transient-local at 5,120).

use std::path::Path;

use cell_runtime::topics::SUITE_TOPICS;

/// One row of the README's topic table: its topics (a row may name several), the message
/// type and the QoS text of each (`a / b` for two topics).
struct Row {
    line: usize,
    topics: Vec<String>,
    type_name: String,
    qos: Vec<String>,
}

/// The backticked words of a table cell.
fn backticked(cell: &str) -> Vec<String> {
    cell.split('`')
        .skip(1)
        .step_by(2)
        .map(str::to_string)
        .collect()
}

/// The numbers written in a text (`5,120` is one number).
fn numbers(text: &str) -> Vec<usize> {
    text.split(|c: char| !(c.is_ascii_digit() || c == ','))
        .map(|w| w.trim_matches(',').replace(',', ""))
        .filter_map(|w| w.parse().ok())
        .collect()
}

fn topic_rows() -> Vec<Row> {
    let readme = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md"))
        .expect("README.md");
    let start = readme
        .lines()
        .position(|l| l == "### Topics")
        .expect("a `### Topics` section");
    readme
        .lines()
        .enumerate()
        .skip(start + 1)
        .skip_while(|(_, l)| !l.starts_with('|'))
        .take_while(|(_, l)| l.starts_with('|'))
        .filter(|(_, l)| l.starts_with("| `/"))
        .map(|(i, l)| {
            let cells: Vec<&str> = l.trim_matches('|').split(" | ").map(str::trim).collect();
            assert_eq!(cells.len(), 3, "README line {}: {l}", i + 1);
            let topics = backticked(cells[0]);
            let qos: Vec<String> = cells[2].split(" / ").map(str::to_string).collect();
            assert_eq!(
                qos.len(),
                topics.len(),
                "README line {}: one QoS per topic",
                i + 1
            );
            Row {
                line: i + 1,
                type_name: backticked(cells[1]).into_iter().next().unwrap_or_default(),
                topics,
                qos,
            }
        })
        .collect()
}

#[test]
fn the_readme_documents_every_topic_with_the_qos_its_publishers_offer() {
    let rows = topic_rows();
    for t in SUITE_TOPICS {
        let found: Vec<(&Row, &String)> = rows
            .iter()
            .flat_map(|r| {
                r.topics
                    .iter()
                    .zip(&r.qos)
                    .map(move |(name, q)| (r, name, q))
            })
            .filter(|(_, name, _)| *name == t.name)
            .map(|(r, _, q)| (r, q))
            .collect();
        assert_eq!(found.len(), 1, "{} must have one row in the README", t.name);
        let (row, qos) = found[0];
        let at = format!("README line {} ({})", row.line, t.name);
        assert_eq!(row.type_name, t.type_name, "{at}");
        assert_eq!(
            qos.contains("transient local"),
            t.qos.transient_local,
            "{at}: durability in `{qos}`"
        );
        assert_eq!(
            qos.contains("volatile"),
            !t.qos.transient_local,
            "{at}: durability in `{qos}`"
        );
        assert_eq!(
            qos.contains("never waits"),
            t.qos.never_wait,
            "{at}: `{qos}`"
        );
        assert!(
            numbers(qos).contains(&t.qos.depth),
            "{at}: depth {} not in `{qos}`",
            t.qos.depth
        );
    }
    for row in &rows {
        for name in &row.topics {
            assert!(
                SUITE_TOPICS.iter().any(|t| t.name == name),
                "README line {}: {name} is no topic of the suite",
                row.line
            );
        }
    }
}

#[test]
fn numbers_are_read_as_written() {
    assert_eq!(numbers("reliable, volatile, 10,000"), [10_000]);
    assert_eq!(numbers("keep-last = window (4096)"), [4096]);
    assert_eq!(
        numbers("transient local, 5,120 (the window and a quarter)"),
        [5120]
    );
}
