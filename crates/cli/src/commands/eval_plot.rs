//! The pictures of `umgen eval`: L2 and the scene's statistics over the horizon, drawn with plotters
//! (axes with ticks and units, a legend) into an RGB buffer that `umgen_viz` writes as a PNG.

use anyhow::Context;
use plotters::prelude::*;
use std::path::Path;
use std::sync::OnceLock;
use umgen_viz::{Rgb, write_png};

/// The plots' font, bundled so that no system font is needed (DejaVu Sans Mono, its licence beside it).
static FONT: &[u8] = include_bytes!("../../assets/DejaVuSansMono.ttf");

/// Pixels of a plot.
const SIZE: (u32, u32) = (780, 440);

/// Pixels on the right that hold the legend, outside the curves.
const LEGEND_W: u32 = 240;

/// One curve: its legend, colour and `(seconds, value)` points, and the points' 95 % intervals as
/// `(seconds, low, high)` whiskers where it has them.
struct Series {
    label: String,
    colour: RGBColor,
    points: Vec<(f64, f64)>,
    bars: Vec<(f64, f64, f64)>,
}

/// A drawn plot, and where each series' points landed.
struct Plot {
    image: Rgb,
    /// Read by the tests, which check the curves' pixels against it.
    #[cfg_attr(not(test), allow(dead_code))]
    at: Vec<Vec<(i32, i32)>>,
}

/// Registers [`FONT`] as plotters' `sans-serif` once per process.
fn font() -> anyhow::Result<()> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED
        .get_or_init(|| plotters::style::register_font("sans-serif", FontStyle::Normal, FONT).is_ok());
    anyhow::ensure!(ok, "the plots' bundled font (DejaVuSansMono.ttf) does not parse");
    Ok(())
}

/// `series` against seconds generated on one chart, y from 0 to a little above the largest value.
fn chart(series: &[Series], title: &str, y_desc: &str) -> anyhow::Result<Plot> {
    font()?;
    let (w, h) = SIZE;
    let mut buf = vec![255u8; (w * h * 3) as usize];
    let mut at = Vec::with_capacity(series.len());
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE)?;
        let (plot_area, legend) = root.split_horizontally(w - LEGEND_W);
        let all = || {
            series
                .iter()
                .flat_map(|s| s.points.iter().copied().chain(s.bars.iter().map(|b| (b.0, b.2))))
        };
        // A little room beyond the last second and the largest value, so no curve runs along the frame.
        let x_max = all().map(|p| p.0).fold(0.0f64, f64::max).max(0.5) * 1.03;
        let y_max = all().map(|p| p.1).fold(0.0f64, f64::max).max(1e-6) * 1.08;
        let mut c = ChartBuilder::on(&plot_area)
            .caption(title, ("sans-serif", 18))
            .margin(14)
            .x_label_area_size(44)
            .y_label_area_size(64)
            .build_cartesian_2d(0f64..x_max, 0f64..y_max)?;
        c.configure_mesh()
            .x_desc("seconds generated (s)")
            .y_desc(y_desc)
            .light_line_style(WHITE)
            .label_style(("sans-serif", 13))
            .draw()?;
        for (i, s) in series.iter().enumerate() {
            c.draw_series(LineSeries::new(s.points.clone(), s.colour.stroke_width(2)))?;
            c.draw_series(
                s.bars
                    .iter()
                    .map(|&(x, lo, hi)| PathElement::new(vec![(x, lo), (x, hi)], s.colour.stroke_width(1))),
            )?;
            at.push(s.points.iter().map(|p| c.backend_coord(p)).collect());
            // The legend: a swatch and the name, one row per series, beside the chart.
            let y = 48 + 20 * i as i32;
            legend.draw(&PathElement::new(vec![(6, y), (30, y)], s.colour.stroke_width(3)))?;
            legend.draw(&Text::new(s.label.as_str(), (38, y - 7), ("sans-serif", 13)))?;
        }
        root.present()?;
    }
    let pixels = buf.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect();
    Ok(Plot {
        image: Rgb {
            width: w as usize,
            height: h as usize,
            pixels,
        },
        at,
    })
}

/// The `(seconds, value)` points of `key` in `rows` (each with `seconds`), where both are numbers.
fn points(rows: &[serde_json::Value], key: &str) -> Vec<(f64, f64)> {
    rows.iter()
        .filter_map(|r| Some((r["seconds"].as_f64()?, r[key].as_f64()?)))
        .collect()
}

/// Curves of ego and agent L2 (model in full colours, constant velocity lighter) over the horizon, as a PNG.
pub fn l2_plot(rows: &[serde_json::Value], path: &Path) -> anyhow::Result<()> {
    write_png(path, &l2_chart(rows)?.image).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// The chart of [`l2_plot`].
fn l2_chart(rows: &[serde_json::Value]) -> anyhow::Result<Plot> {
    let series = [
        ("ego_model", RGBColor(200, 40, 40), "ego, model"),
        (
            "ego_constant_velocity",
            RGBColor(240, 150, 150),
            "ego, constant velocity",
        ),
        ("agents_model", RGBColor(40, 80, 200), "agents, model"),
        (
            "agents_constant_velocity",
            RGBColor(140, 165, 240),
            "agents, constant velocity",
        ),
    ]
    .map(|(key, colour, label)| Series {
        label: label.into(),
        colour,
        points: points(rows, key),
        bars: Vec::new(),
    });
    chart(&series, "L2 against the real positions", "mean L2 (m)")
}

/// Agents per frame, entries and exits per second of the rollouts over the horizon (the rates with their
/// 95 % intervals) against the real split's (the same colours lighter, flat), as a PNG; nothing with
/// fewer than two seconds.
pub fn horizon_plot(horizon: &serde_json::Value, path: &Path) -> anyhow::Result<()> {
    if let Some(plot) = horizon_chart(horizon)? {
        write_png(path, &plot.image).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// The chart of [`horizon_plot`].
fn horizon_chart(horizon: &serde_json::Value) -> anyhow::Result<Option<Plot>> {
    let Some(seconds) = horizon["seconds"].as_array().filter(|r| r.len() >= 2) else {
        return Ok(None);
    };
    // The real levels span the seconds the rollouts reached.
    let (first, last) = seconds
        .iter()
        .filter_map(|r| r["second"].as_f64())
        .fold((f64::MAX, 0.0f64), |(a, b), s| (a.min(s), b.max(s)));
    let mut series = Vec::new();
    // The rates from counts carry their 95 % intervals (`counts`), drawn as whiskers; the entries' a
    // little left of their second and the exits' a little right, so that the two do not cover each other.
    for (key, interval, colour, light, label) in [
        (
            "agents_mean",
            (None, 0.0),
            RGBColor(40, 80, 200),
            RGBColor(140, 165, 240),
            "agents / frame",
        ),
        (
            "entries_per_s",
            (Some("entries_per_s_95"), -0.12),
            RGBColor(30, 150, 60),
            RGBColor(150, 215, 160),
            "entries / s",
        ),
        (
            "exits_per_s",
            (Some("exits_per_s_95"), 0.12),
            RGBColor(200, 40, 40),
            RGBColor(240, 150, 150),
            "exits / s",
        ),
    ] {
        let (interval, shift) = interval;
        let bars: Vec<(f64, f64, f64)> = interval.map_or_else(Vec::new, |ci| {
            seconds
                .iter()
                .filter_map(|r| {
                    let b = &r["generated"]["counts"][ci];
                    Some((r["second"].as_f64()? + shift, b[0].as_f64()?, b[1].as_f64()?))
                })
                .collect()
        });
        let generated: Vec<(f64, f64)> = seconds
            .iter()
            .filter_map(|r| Some((r["second"].as_f64()?, r["generated"][key].as_f64()?)))
            .collect();
        let real = horizon["real"][key]
            .as_f64()
            .map(|v| vec![(first, v), (last, v)])
            .unwrap_or_default();
        series.push(Series {
            label: format!("{label}, generated"),
            colour,
            points: generated,
            bars,
        });
        series.push(Series {
            label: format!("{label}, real"),
            colour: light,
            points: real,
            bars: Vec::new(),
        });
    }
    Ok(Some(chart(
        &series,
        "The scene over the horizon",
        "per frame, per second",
    )?))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn px(img: &Rgb, (x, y): (i32, i32)) -> [u8; 3] {
        img.pixels[y as usize * img.width + x as usize]
    }

    /// Whether `colour` is drawn within two pixels of `p`.
    fn near(img: &Rgb, p: (i32, i32), colour: RGBColor) -> bool {
        (-2..=2).any(|dy| (-2..=2).any(|dx| px(img, (p.0 + dx, p.1 + dy)) == [colour.0, colour.1, colour.2]))
    }

    #[test]
    fn l2_curves_pass_through_their_points_in_order_of_value() {
        let rows: Vec<serde_json::Value> = (1..=4)
            .map(|h| {
                serde_json::json!({"horizon": h, "seconds": 0.5 * h as f64, "ego_model": 1.0 * h as f64,
                    "ego_constant_velocity": 0.5, "agents_model": 8.0, "agents_constant_velocity": null})
            })
            .collect();
        let plot = l2_chart(&rows).unwrap();
        if let Some(p) = std::env::var_os("UMGEN_KEEP_PLOT") {
            write_png(Path::new(&p), &plot.image).unwrap();
        }
        assert_eq!((plot.image.width, plot.image.height), (780, 440));
        // Every point of every drawn series carries its colour; a series without numbers has no points.
        let colours = [
            RGBColor(200, 40, 40),
            RGBColor(240, 150, 150),
            RGBColor(40, 80, 200),
            RGBColor(140, 165, 240),
        ];
        assert_eq!(plot.at.iter().map(Vec::len).collect::<Vec<_>>(), [4, 4, 4, 0]);
        for (points, colour) in plot.at.iter().zip(colours) {
            for &p in points {
                assert!(near(&plot.image, p, colour), "{colour:?} at {p:?}");
            }
        }
        // Larger values lie higher (smaller rows); later seconds further right.
        let (ego, agents) = (&plot.at[0], &plot.at[2]);
        assert!(
            agents[0].1 < ego[3].1 && ego[3].1 < ego[0].1,
            "{ego:?} {agents:?}"
        );
        assert!(ego.windows(2).all(|w| w[0].0 < w[1].0), "{ego:?}");
        // The axes' tick labels and titles are drawn: dark pixels left of the plot area and below it.
        let dark = |xs: std::ops::Range<usize>, ys: std::ops::Range<usize>| {
            ys.flat_map(|y| xs.clone().map(move |x| (x, y)))
                .filter(|&(x, y)| plot.image.pixels[y * 780 + x].iter().all(|&c| c < 100))
                .count()
        };
        assert!(dark(0..60, 40..400) > 100, "y tick labels and title");
        assert!(dark(80..520, 400..440) > 100, "x tick labels and title");
        assert!(dark(580..780, 30..130) > 100, "the legend's names");
    }

    #[test]
    fn the_horizon_chart_draws_the_rollout_against_the_real_level() {
        let seconds: Vec<serde_json::Value> = (1..=3)
            .map(|s| {
                serde_json::json!({"second": s, "generated": {"agents_mean": 10.0 - 3.0 * s as f64,
                    "entries_per_s": 1.5, "exits_per_s": null,
                    "counts": {"entries_per_s_95": [1.0, 2.5], "exits_per_s_95": null}}})
            })
            .collect();
        let horizon = serde_json::json!({"seconds": seconds,
            "real": {"agents_mean": 10.0, "entries_per_s": 2.0, "exits_per_s": 2.0}});
        let plot = horizon_chart(&horizon).unwrap().unwrap();
        // Generated and real series per statistic; exits were never generated, so that curve is empty.
        assert_eq!(
            plot.at.iter().map(Vec::len).collect::<Vec<_>>(),
            [3, 2, 3, 2, 0, 2]
        );
        // The real agents' level (10, the largest value) lies above every generated point, flat.
        let real = &plot.at[1];
        assert_eq!(real[0].1, real[1].1);
        assert!(plot.at[0].iter().all(|p| p.1 > real[0].1), "{:?}", plot.at);
        assert!(near(&plot.image, plot.at[0][2], RGBColor(40, 80, 200)));
        // The entries' whiskers run from 1.0 to 2.5 through the curve at 1.5 (a little left of their
        // second): their colour a third of the way from the curve up to the real level (2.0), on a row
        // the flat curve itself does not reach.
        let (curve, real) = (plot.at[2][1], plot.at[3][0]);
        let row = curve.1 + (real.1 - curve.1) / 3;
        assert!(real.1 < row && row < curve.1 - 3, "{curve:?} {real:?}");
        let green = (curve.0 - 40..curve.0).filter(|&x| px(&plot.image, (x, row)) == [30, 150, 60]);
        assert!(green.count() > 0, "no whisker left of {curve:?} on row {row}");
        assert!(
            horizon_chart(&serde_json::json!({"seconds": [], "real": {}}))
                .unwrap()
                .is_none()
        );
    }
}
