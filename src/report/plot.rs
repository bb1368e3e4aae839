//! PNG plots with plotters' bitmap backend. Text uses the DejaVu Sans Mono font embedded from
//! assets/fonts (no system font needed). Logarithmic axes are drawn by plotting log10 of the
//! values and labelling the ticks with the values themselves.

use std::path::Path;
use std::sync::Once;

use anyhow::{anyhow, Result};
use plotters::prelude::*;

use crate::image::io::write_png;
use crate::image::Image;

static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSansMono.ttf");
pub(crate) const FAMILY: &str = "sans-serif";
const SIZE: (u32, u32) = (800, 500);

pub(crate) fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The bytes are a valid TTF committed with the crate; a failure would only lose the text.
        let _ = plotters::style::register_font(FAMILY, FontStyle::Normal, FONT);
    });
}

#[derive(Clone, Debug)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

#[derive(Clone, Debug)]
pub struct LinePlot {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub log_y: bool,
    pub series: Vec<Series>,
}

#[derive(Clone, Debug)]
pub struct ScatterPoint {
    pub label: String,
    pub x: f64,
    pub y: f64,
    pub group: String,
}

/// Finite range of values with a margin; a single value gets a unit-wide range.
fn range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values.filter(|v| v.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = if hi > lo { 0.05 * (hi - lo) } else { 0.5 };
    (lo - pad, hi + pad)
}

fn axis_value(v: f64, log: bool) -> Option<f64> {
    let t = if log { if v > 0.0 { v.log10() } else { f64::NAN } } else { v };
    t.is_finite().then_some(t)
}

fn tick_label(v: f64, log: bool) -> String {
    if log {
        let x = 10f64.powf(v);
        if (1e-2..1e4).contains(&x.abs()) { format!("{x:.3}") } else { format!("{x:.1e}") }
    } else {
        format!("{v:.3}")
    }
}

fn save(buffer: Vec<u8>, path: &Path) -> Result<()> {
    let img = Image { width: SIZE.0 as usize, height: SIZE.1 as usize, channels: 3, data: buffer.iter().map(|&b| b as f32 / 255.0).collect() };
    write_png(path, &img)
}

fn err<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow!("plotting: {e}")
}

/// Writes `plot` as an 800×500 PNG. Non-finite points (and non-positive ones on a log axis) are
/// skipped; empty series are drawn as legend entries only.
pub fn write_line_plot(plot: &LinePlot, path: &Path) -> Result<()> {
    register_font();
    let series: Vec<Vec<(f64, f64)>> = plot
        .series
        .iter()
        .map(|s| s.points.iter().filter_map(|&(x, y)| Some((axis_value(x, false)?, axis_value(y, plot.log_y)?))).collect())
        .collect();
    let (x0, x1) = range(series.iter().flatten().map(|p| p.0));
    let (y0, y1) = range(series.iter().flatten().map(|p| p.1));
    let mut buffer = vec![255u8; (SIZE.0 * SIZE.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, SIZE).into_drawing_area();
        root.fill(&WHITE).map_err(err)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(&plot.title, (FAMILY, 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(err)?;
        let log = plot.log_y;
        chart
            .configure_mesh()
            .x_desc(plot.x_label.as_str())
            .y_desc(plot.y_label.as_str())
            .y_label_formatter(&|v| tick_label(*v, log))
            .x_label_formatter(&|v| if x1 - x0 < 20.0 { format!("{v:.1}") } else { format!("{v:.0}") })
            .label_style((FAMILY, 13))
            .draw()
            .map_err(err)?;
        for (k, (s, pts)) in plot.series.iter().zip(&series).enumerate() {
            let colour = Palette99::pick(k).to_rgba();
            chart
                .draw_series(LineSeries::new(pts.iter().copied(), colour.stroke_width(2)))
                .map_err(err)?
                .label(s.name.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
        }
        chart
            .configure_series_labels()
            .label_font((FAMILY, 13))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(err)?;
        root.present().map_err(err)?;
    }
    save(buffer, path)
}

/// Writes a scatter of `points` (coloured by group) with the Pareto front (minimise x, maximise y)
/// as a step line whose points carry their labels.
pub fn write_pareto_plot(points: &[ScatterPoint], x_label: &str, y_label: &str, title: &str, log_x: bool, path: &Path) -> Result<()> {
    register_font();
    let xy: Vec<Option<(f64, f64)>> = points.iter().map(|p| Some((axis_value(p.x, log_x)?, axis_value(p.y, false)?))).collect();
    let (x0, x1) = range(xy.iter().flatten().map(|p| p.0));
    let (y0, y1) = range(xy.iter().flatten().map(|p| p.1));
    let raw: Vec<(f64, f64)> = points.iter().map(|p| (p.x, p.y)).collect();
    let front = super::pareto::pareto_front(&raw);
    let mut groups: Vec<&str> = Vec::new();
    for p in points {
        if !groups.contains(&p.group.as_str()) {
            groups.push(&p.group);
        }
    }
    let mut buffer = vec![255u8; (SIZE.0 * SIZE.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, SIZE).into_drawing_area();
        root.fill(&WHITE).map_err(err)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, (FAMILY, 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(y_label)
            .x_label_formatter(&|v| tick_label(*v, log_x))
            .y_label_formatter(&|v| format!("{v:.1}"))
            .label_style((FAMILY, 13))
            .draw()
            .map_err(err)?;
        for (k, g) in groups.iter().enumerate() {
            let colour = Palette99::pick(k).to_rgba();
            let members: Vec<(f64, f64)> = points.iter().zip(&xy).filter(|(p, _)| p.group == *g).filter_map(|(_, c)| *c).collect();
            chart
                .draw_series(members.into_iter().map(move |c| Circle::new(c, 5, colour.filled())))
                .map_err(err)?
                .label(*g)
                .legend(move |(x, y)| Circle::new((x + 10, y), 5, colour.filled()));
        }
        let front_xy: Vec<(f64, f64)> = front.iter().filter_map(|&i| xy[i]).collect();
        let mut steps = Vec::new();
        for (k, &(x, y)) in front_xy.iter().enumerate() {
            if k > 0 {
                steps.push((x, front_xy[k - 1].1));
            }
            steps.push((x, y));
        }
        chart
            .draw_series(LineSeries::new(steps, BLACK.stroke_width(2)))
            .map_err(err)?
            .label("Pareto front")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.stroke_width(2)));
        for &i in &front {
            if let Some(c) = xy[i] {
                chart.draw_series(std::iter::once(Text::new(points[i].label.clone(), c, (FAMILY, 12)))).map_err(err)?;
            }
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .label_font((FAMILY, 13))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(err)?;
        root.present().map_err(err)?;
    }
    save(buffer, path)
}
