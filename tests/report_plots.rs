//! Report graphics: a line plot and a Pareto plot are written as PNGs of the requested size that
//! carry the series colours (not blank), including degenerate inputs (empty, single, constant,
//! non-finite points).

use reconstruct::image::io::read_png;
use reconstruct::report::plot::{write_line_plot, write_pareto_plot, LinePlot, ScatterPoint, Series};

fn non_white_fraction(path: &std::path::Path) -> f64 {
    let img = read_png(path).expect("plot decodes");
    assert_eq!((img.width, img.height), (800, 500));
    let coloured = img.data.chunks_exact(img.channels).filter(|p| p[..3].iter().any(|&v| v < 0.9) && (p[0] - p[1]).abs() + (p[1] - p[2]).abs() > 0.2).count();
    coloured as f64 / (img.width * img.height) as f64
}

#[test]
fn line_and_pareto_plots_are_written_and_not_blank() -> anyhow::Result<()> {
    let dir = std::env::temp_dir().join(format!("reconstruct-plots-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let loss = LinePlot {
        title: "loss".into(),
        x_label: "iteration".into(),
        y_label: "loss".into(),
        log_y: true,
        series: vec![
            Series { name: "total".into(), points: (0..200).map(|i| (i as f64, 1.0 / (1.0 + i as f64))).collect() },
            Series { name: "with junk".into(), points: vec![(0.0, f64::NAN), (1.0, -1.0), (2.0, 0.5), (3.0, f64::INFINITY)] },
            Series { name: "empty".into(), points: vec![] },
        ],
    };
    let path = dir.join("loss.png");
    write_line_plot(&loss, &path)?;
    assert!(non_white_fraction(&path) > 0.001, "no coloured line drawn");
    // Degenerate: one constant point.
    let single = LinePlot { series: vec![Series { name: "one".into(), points: vec![(5.0, 2.0)] }], log_y: false, ..loss.clone() };
    write_line_plot(&single, &dir.join("single.png"))?;
    let pts: Vec<ScatterPoint> = (0..12)
        .map(|i| ScatterPoint { label: format!("p{i}"), x: 1.0 + i as f64 * 3.0, y: 20.0 + ((i * 7) % 5) as f64, group: if i % 2 == 0 { "split-sum".into() } else { "MC".into() } })
        .collect();
    let path = dir.join("pareto.png");
    write_pareto_plot(&pts, "seconds", "PSNR (dB)", "trade-off", true, &path)?;
    assert!(non_white_fraction(&path) > 0.001, "no coloured points drawn");
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}
