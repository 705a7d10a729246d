//! Plots in the paper's style: the output (blue, solid) against the reference (red, dashed)
//! above, the applied voltage below; one PNG and one SVG per channel. The axes tick at
//! round values with plain labels and carry their unit ([`crate::chart`]).

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::{RunRecordError, Trace};
use crate::chart::{axis_title, ensure_font, Ticks};

type Result<T> = std::result::Result<T, RunRecordError>;

fn plot_error(path: &Path, e: impl std::fmt::Debug) -> RunRecordError {
    RunRecordError::Plot {
        path: path.to_path_buf(),
        reason: format!("{e:?}"),
    }
}

/// Draw one channel to `DIR/NAME.png` and `DIR/NAME.svg`.
pub fn channel(
    dir: &Path,
    name: &str,
    unit: &str,
    title: &str,
    t: &[f64],
    trace: &Trace,
) -> Result<()> {
    ensure_font();
    let png = dir.join(format!("{name}.png"));
    let svg = dir.join(format!("{name}.svg"));
    {
        let root = BitMapBackend::new(&png, (1000, 700)).into_drawing_area();
        draw(&root, name, unit, title, t, trace).map_err(|e| plot_error(&png, e))?;
        root.present().map_err(|e| plot_error(&png, e))?;
    }
    {
        let root = SVGBackend::new(&svg, (1000, 700)).into_drawing_area();
        draw(&root, name, unit, title, t, trace).map_err(|e| plot_error(&svg, e))?;
        root.present().map_err(|e| plot_error(&svg, e))?;
    }
    Ok(())
}

fn range(series: &[&[f64]]) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::MAX, f64::MIN);
    for s in series {
        for v in s.iter().filter(|v| v.is_finite()) {
            lo = lo.min(*v);
            hi = hi.max(*v);
        }
    }
    if lo > hi {
        return (-1.0, 1.0);
    }
    let pad = ((hi - lo) * 0.08).max(1e-9);
    (lo - pad, hi + pad)
}

/// Ticks on the time axis: at most ten, `0, 5, 10, ...`.
const TIME_TICKS: usize = 10;

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    name: &str,
    unit: &str,
    title: &str,
    t: &[f64],
    trace: &Trace,
) -> std::result::Result<(), String>
where
    DB::ErrorType: 'static,
{
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| format!("drawing {name}: {e:?}");
    root.fill(&WHITE).map_err(err)?;
    let root = root.titled(title, ("sans-serif", 22)).map_err(err)?;
    let (top, bottom) = root.split_vertically((62).percent());
    let t_end = t.last().copied().unwrap_or(1.0).max(1e-9);
    let time = Ticks::linear(0.0, t_end, TIME_TICKS);
    outputs(&top, (name, unit), (t, &time, t_end), trace).map_err(err)?;
    inputs(&bottom, (t, &time, t_end), &trace.v).map_err(err)?;
    Ok(())
}

/// The output (blue, solid) against the reference (red, dashed).
fn outputs<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    (name, unit): (&str, &str),
    (t, time, t_end): (&[f64], &Ticks, f64),
    trace: &Trace,
) -> std::result::Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let (lo, hi) = range(&[&trace.y, &trace.y_ref]);
    let ticks = Ticks::linear(lo, hi, 8);
    let mut chart = ChartBuilder::on(area)
        .margin(10)
        .margin_right(30)
        .x_label_area_size(35)
        .y_label_area_size(80)
        .build_cartesian_2d(time.axis(0.0..t_end), ticks.axis(lo..hi))?;
    chart
        .configure_mesh()
        .x_desc(axis_title("time", "s"))
        .y_desc(axis_title(name, unit))
        .x_label_formatter(&|v| time.label(*v))
        .y_label_formatter(&|v| ticks.label(*v))
        .draw()?;
    chart
        .draw_series(LineSeries::new(
            t.iter().copied().zip(trace.y.iter().copied()),
            BLUE.stroke_width(2),
        ))?
        .label("output")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
    chart.draw_series(DashedLineSeries::new(
        t.iter().copied().zip(trace.y_ref.iter().copied()),
        8,
        6,
        RED.stroke_width(2),
    ))?;
    chart
        .draw_series(std::iter::empty::<PathElement<(f64, f64)>>())?
        .label("reference")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.stroke_width(2)));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .draw()
}

/// The applied input `v`, below.
fn inputs<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    (t, time, t_end): (&[f64], &Ticks, f64),
    v: &[f64],
) -> std::result::Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let (lo, hi) = range(&[v]);
    let ticks = Ticks::linear(lo, hi, 6);
    let mut chart = ChartBuilder::on(area)
        .margin(10)
        .margin_right(30)
        .x_label_area_size(35)
        .y_label_area_size(80)
        .build_cartesian_2d(time.axis(0.0..t_end), ticks.axis(lo..hi))?;
    chart
        .configure_mesh()
        .x_desc(axis_title("time", "s"))
        .y_desc(axis_title("applied input", "V"))
        .x_label_formatter(&|v| time.label(*v))
        .y_label_formatter(&|v| ticks.label(*v))
        .draw()?;
    chart.draw_series(LineSeries::new(
        t.iter().copied().zip(v.iter().copied()),
        BLACK.stroke_width(1),
    ))?;
    Ok(())
}
