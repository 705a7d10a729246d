//! `aero-sim`: the simulated AERO as a plant driver on stdin/stdout (the reference driver
//! of `plant-agent/DRIVER.md`). Try:
//! `printf 'read\nwrite 12 -3\nadvance 0.5\nread\nstop\n' | aero-sim`.

use anyhow::Result;
use clap::Parser;

#[derive(Parser)]
#[command(
    name = "aero-sim",
    version,
    about = "The simulated Quanser AERO as a plant driver on stdin/stdout"
)]
struct Cli {
    /// Noise seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Add the paper's 4 g mass at the rotor arm.
    #[arg(long)]
    added_mass: bool,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let mut params = aero_sim::AeroParams::default();
    if cli.added_mass {
        params.added_mass = aero_sim::PAPER_ADDED_MASS;
    }
    aero_sim::driver::serve(
        params,
        cli.seed,
        std::io::stdin().lock(),
        std::io::stdout().lock(),
    )?;
    Ok(())
}
