//! Plots in the paper's style: the output (blue, solid) against the reference (red, dashed)
//! above, the applied voltage below; one PNG and one SVG per channel.

use std::path::Path;
use std::sync::Once;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontStyle;

use super::{RecordError, Trace};

type Result<T> = std::result::Result<T, RecordError>;

fn plot_error(path: &Path, e: impl std::fmt::Debug) -> RecordError {
    RecordError::Plot {
        path: path.to_path_buf(),
        reason: format!("{e:?}"),
    }
}

static FONT: Once = Once::new();

/// The bitmap backend draws text with an embedded font (no system fonts needed, so plots
/// work on a bare server); call before drawing any PNG.
pub fn ensure_font() {
    FONT.call_once(|| {
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
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

    let (lo, hi) = range(&[&trace.y, &trace.y_ref]);
    let mut chart = ChartBuilder::on(&top)
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(80)
        .build_cartesian_2d(0.0..t_end, lo..hi)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("time (s)")
        .y_desc(format!("{name} ({unit})"))
        .y_label_formatter(&|v| format!("{v:.3e}"))
        .light_line_style(WHITE.mix(0.0))
        .draw()
        .map_err(err)?;
    chart
        .draw_series(LineSeries::new(
            t.iter().copied().zip(trace.y.iter().copied()),
            BLUE.stroke_width(2),
        ))
        .map_err(err)?
        .label("output")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLUE.stroke_width(2)));
    chart
        .draw_series(DashedLineSeries::new(
            t.iter().copied().zip(trace.y_ref.iter().copied()),
            8,
            6,
            RED.stroke_width(2),
        ))
        .map_err(err)?;
    chart
        .draw_series(std::iter::empty::<PathElement<(f64, f64)>>())
        .map_err(err)?
        .label("reference")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.stroke_width(2)));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(err)?;

    let (lo, hi) = range(&[&trace.v]);
    let mut chart = ChartBuilder::on(&bottom)
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(80)
        .build_cartesian_2d(0.0..t_end, lo..hi)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("time (s)")
        .y_desc("voltage (V)")
        .light_line_style(WHITE.mix(0.0))
        .draw()
        .map_err(err)?;
    chart
        .draw_series(LineSeries::new(
            t.iter().copied().zip(trace.v.iter().copied()),
            BLACK.stroke_width(1),
        ))
        .map_err(err)?;
    Ok(())
}
