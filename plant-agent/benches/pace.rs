//! How late the agent's period deadline wakes: `plant_agent::pace::sleep_until` beside
//! tokio's own `sleep_until` (the anchor), in the same run, on the agent's schedule (a
//! 10 ms period, deadlines `start + k h` that never drift).
//!
//! `cargo bench -p plant-agent --bench pace [-- PERIODS]` (default 300 per round, three
//! rounds, the two alternating so that both see the same machine). Prints the median, the
//! 90th and the 99th percentile of the lateness, and the ratios to the anchor.

use std::time::Duration;

use tokio::time::Instant;

fn percentile(sorted: &[f64], p: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let periods: u32 = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .and_then(|a| a.parse().ok())
        .unwrap_or(300);
    let h = Duration::from_millis(10);
    let (mut tokio_late, mut pace_late) = (Vec::new(), Vec::new());
    for round in 0..3 {
        for precise in [false, true] {
            let start = Instant::now() + h;
            for k in 0..periods {
                let deadline = start + h * k;
                if precise {
                    plant_agent::pace::sleep_until(deadline).await;
                } else {
                    tokio::time::sleep_until(deadline).await;
                }
                let late = Instant::now().duration_since(deadline).as_secs_f64() * 1e6;
                if precise {
                    pace_late.push(late);
                } else {
                    tokio_late.push(late);
                }
            }
        }
        eprintln!("round {} of 3 done", round + 1);
    }
    tokio_late.sort_by(f64::total_cmp);
    pace_late.sort_by(f64::total_cmp);
    println!("| wait | periods | median late (us) | p90 (us) | p99 (us) |");
    println!("|---|---:|---:|---:|---:|");
    for (name, v) in [
        ("tokio::time::sleep_until (anchor)", &tokio_late),
        ("pace::sleep_until", &pace_late),
    ] {
        println!(
            "| {name} | {} | {:.0} | {:.0} | {:.0} |",
            v.len(),
            percentile(v, 0.5),
            percentile(v, 0.9),
            percentile(v, 0.99)
        );
    }
    println!(
        "\nratio to the anchor: median {:.2}, p99 {:.2}",
        percentile(&pace_late, 0.5) / percentile(&tokio_late, 0.5),
        percentile(&pace_late, 0.99) / percentile(&tokio_late, 0.99)
    );
}
