//! Writing a run to disk: `timeseries.csv`, `summary.json` and the plots.

use std::fs;
use std::io::{BufWriter, Write};
use std::path::Path;

use anyhow::{Context, Result};

use crate::offline::Run;
use crate::plot;
use crate::scenario::Scenario;

/// Write `timeseries.csv`, `summary.json` and one PNG and one SVG per channel into `dir`.
pub fn write_run(dir: &Path, scenario: &Scenario, run: &Run) -> Result<()> {
    fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    write_csv(&dir.join("timeseries.csv"), scenario, run)?;
    let json = serde_json::to_string_pretty(&run.summary)?;
    fs::write(dir.join("summary.json"), json + "\n")
        .with_context(|| format!("writing {}", dir.join("summary.json").display()))?;
    for (i, c) in scenario.channels.iter().enumerate() {
        let title = format!(
            "{} — {} — {}",
            scenario.name, run.summary.controller, c.name
        );
        plot::channel(dir, &c.name, &c.unit, &title, &run.t, &run.traces[i])?;
    }
    Ok(())
}

fn write_csv(path: &Path, scenario: &Scenario, run: &Run) -> Result<()> {
    let file = fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut w = BufWriter::new(file);
    write!(w, "t")?;
    for c in &scenario.channels {
        let n = &c.name;
        write!(w, ",{n}_ref,{n},{n}_u,{n}_v,{n}_f_est")?;
    }
    writeln!(w)?;
    for (k, t) in run.t.iter().enumerate() {
        write!(w, "{t:.4}")?;
        for tr in &run.traces {
            write!(
                w,
                ",{:e},{:e},{:e},{:e},{}",
                tr.y_ref[k],
                tr.y[k],
                tr.u[k],
                tr.v[k],
                if tr.f_est[k].is_nan() {
                    String::new()
                } else {
                    format!("{:e}", tr.f_est[k])
                }
            )?;
        }
        writeln!(w)?;
    }
    w.flush()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
