//! Lid-driven cavity against Ghia, Ghia & Shin (1982) on a sequence of grids:
//! `cargo run --release -p screw_driver --example cavity -- [CELLS...]`.
use screw_driver::flow::ghia;

fn main() {
    let cells: Vec<usize> = std::env::args()
        .skip(1)
        .map(|a| a.parse().expect("cells per side"))
        .collect();
    let cells = if cells.is_empty() {
        vec![32, 64, 128]
    } else {
        cells
    };
    println!("Re    cells  steps   t_end   max|u-Ghia|  max|v-Ghia|  seconds");
    for re in [100u32, 1000] {
        for &n in &cells {
            let started = std::time::Instant::now();
            let flow = ghia::solve_cavity(re as f64, n).expect("cavity");
            let (du, dv) = ghia::compare(&flow, re).expect("table");
            println!(
                "{re:<5} {n:>5} {:>7} {:>7.1} {du:>12.5} {dv:>12.5} {:>8.1}",
                flow.steps(),
                flow.time(),
                started.elapsed().as_secs_f64()
            );
        }
    }
}
