//! Baseline for the streamer's figure: the raw ros2-client transport, two participants in one
//! process on loopback, one reliable topic of `GcodeMove`, publishing as fast as `publish`
//! accepts, no application-level flow control. Prints messages/s sent and received and the
//! number lost.
//!
//!     cargo run --release --example dds_raw_throughput -- 200000

use std::time::{Duration, Instant};

use cell_runtime::{reliable_qos, CellNode, RosArgs};
use polar_cell_msgs::GcodeMove;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let count: u64 = std::env::args()
        .nth(1)
        .map(|a| a.parse())
        .transpose()?
        .unwrap_or(200_000);
    let args = RosArgs::default();
    let mut sender = CellNode::start("raw_sender", &[], &args)?;
    let mut receiver = CellNode::start("raw_receiver", &[], &args)?;
    let qos = reliable_qos(10_000);
    let publisher = sender.publisher::<GcodeMove>("/raw/moves", &qos)?;
    let subscription = receiver.subscription::<GcodeMove>("/raw/moves", &qos)?;
    publisher.wait_for_subscription(&sender.node).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let receive = tokio::spawn(async move {
        let mut received = 0u64;
        let mut last = None;
        let start = Instant::now();
        let mut out_of_order = 0u64;
        while let Ok(Ok((m, _))) =
            tokio::time::timeout(Duration::from_secs(2), subscription.async_take()).await
        {
            if last.is_some_and(|l| m.sequence <= l) {
                out_of_order += 1;
            }
            last = Some(m.sequence);
            received += 1;
            if m.sequence + 1 == count {
                break;
            }
        }
        (received, out_of_order, start.elapsed())
    });
    let start = Instant::now();
    let mut failed = 0u64;
    for sequence in 0..count {
        let mut m = GcodeMove {
            sequence,
            ..Default::default()
        };
        loop {
            match publisher.publish(m) {
                Ok(()) => break,
                Err(ros2_client::ros2::WriteError::WouldBlock { data }) => {
                    failed += 1;
                    m = data;
                }
                Err(e) => anyhow::bail!("publish: {e:?}"),
            }
        }
    }
    let sent_in = start.elapsed();
    let (received, out_of_order, received_in) = receive.await?;
    println!(
        "sent {count} in {:.3} s ({:.0}/s, {failed} would-block retries); received {received} ({:.0}/s), lost {}, out of order {out_of_order}",
        sent_in.as_secs_f64(),
        count as f64 / sent_in.as_secs_f64(),
        received as f64 / received_in.as_secs_f64(),
        count - received
    );
    Ok(())
}
