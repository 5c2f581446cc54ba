//! Bag writer throughput: GcodeMove messages (CDR-encoded, as the recorder receives them)
//! written with zstd and with lz4 chunks to a file under the system temp directory, including
//! `finish()` (summary, indexes).

use std::io::BufWriter;

use cell_bag::{BagWriter, Compression, QosRecord, WriterOptions};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use polar_cell_msgs::{cdr, GcodeMove, RosMessage};

const MESSAGES: u64 = 1_000_000;

fn record(compression: Compression, encoded: &[Vec<u8>]) -> u64 {
    let path = std::env::temp_dir().join(format!("cell_bag_bench_{}.mcap", std::process::id()));
    let file = std::fs::File::create(&path).expect("temp file");
    let options = WriterOptions {
        compression,
        ..WriterOptions::default()
    };
    let mut bag = BagWriter::new(BufWriter::with_capacity(1 << 20, file), &options).unwrap();
    let channel = bag
        .add_topic("/gcode/moves", GcodeMove::TYPE, QosRecord::ROS_DEFAULT)
        .unwrap();
    for (i, data) in encoded.iter().enumerate() {
        let t = 1_000_000_000 + i as u64 * 1000;
        bag.write(channel, t, t, data).unwrap();
    }
    let count = bag.message_count();
    bag.finish().unwrap();
    std::fs::remove_file(&path).ok();
    count
}

fn bench(c: &mut Criterion) {
    // Realistic contents: a spiral, so chunks compress like real moves do.
    let encoded: Vec<Vec<u8>> = (0..MESSAGES)
        .map(|i| {
            let a = i as f64 * 0.01;
            cdr::encode(&GcodeMove {
                sequence: i,
                source_line: i as u32 + 5,
                kind: GcodeMove::KIND_LINEAR,
                segment_count: 1,
                x_m: 0.03 * a.cos(),
                y_m: 0.03 * a.sin(),
                z_m: 0.0002 * (i / 500) as f64,
                e_m: i as f64 * 1e-5,
                delta_e_m: 1e-5,
                feedrate_m_per_s: 0.05,
                extrude: true,
                ..Default::default()
            })
            .unwrap()
        })
        .collect();
    let mut group = c.benchmark_group("bag_write");
    group.throughput(Throughput::Elements(MESSAGES));
    group.sample_size(10);
    group.bench_function("zstd_1M_moves", |b| {
        b.iter(|| record(Compression::Zstd, &encoded))
    });
    group.bench_function("lz4_1M_moves", |b| {
        b.iter(|| record(Compression::Lz4, &encoded))
    });
    group.bench_function("encode_and_zstd_1M_moves", |b| {
        b.iter(|| {
            let fresh: Vec<Vec<u8>> = encoded
                .iter()
                .map(|d| cdr::encode(&cdr::decode::<GcodeMove>(d).unwrap()).unwrap())
                .collect();
            record(Compression::Zstd, &fresh)
        })
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
