//! The convergence plot (`convergence.png` of a reconstruction, `convergence.svg` on the status
//! page): the score at the end of every level and refinement sweep against the photons spent
//! so far, and the pixel accuracy beside it when the truth is known (the paper's Fig. 6 kind
//! of curve). One layout draws both formats, so they show the same thing.

use crate::picture::draw_text;
use crate::report::ConvergenceReport;
use image::{Rgb, RgbImage};
use std::fmt::Write as _;

const WIDTH: u32 = 640;
const HEIGHT: u32 = 340;
const LEFT: f64 = 88.0;
const RIGHT: f64 = 72.0;
const TOP: f64 = 34.0;
const BOTTOM: f64 = 48.0;

const SCORE: Rgb<u8> = Rgb([50, 100, 180]);
const ACCURACY: Rgb<u8> = Rgb([40, 150, 70]);
const AXIS: Rgb<u8> = Rgb([0, 0, 0]);
const GRID: Rgb<u8> = Rgb([225, 225, 225]);
const REFINE: Rgb<u8> = Rgb([200, 120, 40]);

/// Where everything goes, in pixels, for one curve.
struct Layout {
    photons: (f64, f64),
    score: (f64, f64),
    accuracy: Option<(f64, f64)>,
    /// (photons, score, accuracy) of each point, in order.
    points: Vec<(f64, f64, Option<f64>)>,
    /// The photons where refinement starts (the first sweep's predecessor), if it does.
    refine_from: Option<f64>,
    unit: (f64, &'static str),
}

fn span((lo, hi): (f64, f64)) -> (f64, f64) {
    if (hi - lo).abs() < 1e-12 {
        let pad = if lo.abs() > 1e-12 {
            lo.abs() * 0.05
        } else {
            1.0
        };
        (lo - pad, hi + pad)
    } else {
        let pad = (hi - lo) * 0.05;
        (lo - pad, hi + pad)
    }
}

impl Layout {
    fn new(curve: &[ConvergenceReport]) -> Option<Layout> {
        let points: Vec<(f64, f64, Option<f64>)> = curve
            .iter()
            .filter(|p| p.score.is_finite())
            .map(|p| (p.photons as f64, p.score, p.pixel_accuracy))
            .collect();
        if points.is_empty() {
            return None;
        }
        let max_photons = points.iter().map(|p| p.0).fold(0.0, f64::max).max(1.0);
        let score = points
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                (lo.min(p.1), hi.max(p.1))
            });
        let accuracies: Vec<f64> = points.iter().filter_map(|p| p.2).collect();
        let accuracy = (!accuracies.is_empty()).then(|| {
            let lo = accuracies.iter().copied().fold(1.0, f64::min);
            ((lo * 20.0).floor() / 20.0, 1.0)
        });
        let refine_from = curve
            .iter()
            .position(|p| p.stage == "sweep")
            .and_then(|i| i.checked_sub(1))
            .map(|i| curve[i].photons as f64);
        let unit = if max_photons >= 1e9 {
            (1e9, "G")
        } else if max_photons >= 1e6 {
            (1e6, "M")
        } else {
            (1e3, "k")
        };
        Some(Layout {
            photons: (0.0, max_photons * 1.03),
            score: span(score),
            accuracy,
            points,
            refine_from,
            unit,
        })
    }

    fn x(&self, photons: f64) -> f64 {
        LEFT + (photons - self.photons.0) / (self.photons.1 - self.photons.0)
            * (f64::from(WIDTH) - LEFT - RIGHT)
    }

    fn y(range: (f64, f64), v: f64) -> f64 {
        let h = f64::from(HEIGHT) - TOP - BOTTOM;
        TOP + (1.0 - (v - range.0) / (range.1 - range.0)) * h
    }

    fn y_score(&self, v: f64) -> f64 {
        Layout::y(self.score, v)
    }

    fn y_accuracy(&self, v: f64) -> Option<f64> {
        self.accuracy.map(|r| Layout::y(r, v))
    }

    /// Five evenly spaced values over `range`.
    fn ticks(range: (f64, f64)) -> Vec<f64> {
        (0..5)
            .map(|i| range.0 + (range.1 - range.0) * f64::from(i) / 4.0)
            .collect()
    }

    /// A score tick's label, with enough decimals to tell the five ticks of `range` apart.
    fn score_label(v: f64, range: (f64, f64)) -> String {
        if v.abs() >= 1e7 {
            return format!("{v:.3e}");
        }
        let step = ((range.1 - range.0) / 4.0).abs().max(1e-12);
        let decimals = (-step.log10()).ceil().max(0.0) as usize;
        format!("{v:.decimals$}")
    }

    fn score_polyline(&self) -> Vec<(f64, f64)> {
        self.points
            .iter()
            .map(|p| (self.x(p.0), self.y_score(p.1)))
            .collect()
    }

    fn accuracy_polyline(&self) -> Vec<(f64, f64)> {
        self.points
            .iter()
            .filter_map(|p| Some((self.x(p.0), self.y_accuracy(p.2?)?)))
            .collect()
    }
}

/// The plot as a PNG image; `None` when the curve has no point yet.
pub fn png(curve: &[ConvergenceReport]) -> Option<RgbImage> {
    let l = Layout::new(curve)?;
    let mut img = RgbImage::from_pixel(WIDTH, HEIGHT, Rgb([255, 255, 255]));
    let (x0, x1) = (LEFT, f64::from(WIDTH) - RIGHT);
    let (y0, y1) = (TOP, f64::from(HEIGHT) - BOTTOM);
    for v in Layout::ticks(l.score) {
        let y = l.y_score(v);
        line(&mut img, (x0, y), (x1, y), GRID);
        let text = Layout::score_label(v, l.score);
        let w = 8.0 * text.len() as f64;
        draw_text(
            &mut img,
            (x0 - 6.0 - w).max(0.0) as u32,
            (y - 4.0) as u32,
            &text,
            1,
            SCORE,
        );
    }
    if let Some(r) = l.accuracy {
        for v in Layout::ticks(r) {
            let y = Layout::y(r, v);
            let text = format!("{:.0} %", v * 100.0);
            draw_text(
                &mut img,
                (x1 + 6.0) as u32,
                (y - 4.0) as u32,
                &text,
                1,
                ACCURACY,
            );
        }
    }
    for v in Layout::ticks(l.photons) {
        let x = l.x(v);
        line(&mut img, (x, y1), (x, y1 + 4.0), AXIS);
        let text = format!("{:.2}", v / l.unit.0);
        draw_text(
            &mut img,
            (x - 4.0 * text.len() as f64) as u32,
            (y1 + 8.0) as u32,
            &text,
            1,
            AXIS,
        );
    }
    line(&mut img, (x0, y0), (x0, y1), AXIS);
    line(&mut img, (x0, y1), (x1, y1), AXIS);
    line(&mut img, (x1, y0), (x1, y1), AXIS);
    if let Some(p) = l.refine_from {
        let x = l.x(p);
        line(&mut img, (x, y0), (x, y1), REFINE);
        draw_text(
            &mut img,
            (x + 3.0) as u32,
            (y0 + 3.0) as u32,
            "refinement",
            1,
            REFINE,
        );
    }
    let xlabel = format!("photons spent ({} photons, all sources)", l.unit.1);
    draw_text(
        &mut img,
        (x0 + (x1 - x0) / 2.0 - 4.0 * xlabel.len() as f64) as u32,
        HEIGHT - 18,
        &xlabel,
        1,
        AXIS,
    );
    draw_text(&mut img, 8, 8, "score", 2, SCORE);
    if l.accuracy.is_some() {
        draw_text(&mut img, WIDTH - 8 - 16 * 8, 8, "accuracy", 2, ACCURACY);
    }
    for (series, colour) in [
        (l.score_polyline(), SCORE),
        (l.accuracy_polyline(), ACCURACY),
    ] {
        for w in series.windows(2) {
            line(&mut img, w[0], w[1], colour);
            line(
                &mut img,
                (w[0].0, w[0].1 + 1.0),
                (w[1].0, w[1].1 + 1.0),
                colour,
            );
        }
        for &(x, y) in &series {
            for dy in -2..=2 {
                for dx in -2..=2 {
                    put(&mut img, x + f64::from(dx), y + f64::from(dy), colour);
                }
            }
        }
    }
    Some(img)
}

/// The plot as an SVG document; `None` when the curve has no point yet.
pub fn svg(curve: &[ConvergenceReport]) -> Option<String> {
    let l = Layout::new(curve)?;
    let (x0, x1) = (LEFT, f64::from(WIDTH) - RIGHT);
    let (y0, y1) = (TOP, f64::from(HEIGHT) - BOTTOM);
    let hex = |c: Rgb<u8>| format!("#{:02x}{:02x}{:02x}", c.0[0], c.0[1], c.0[2]);
    let mut s = String::new();
    let _ = write!(
        s,
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{WIDTH}\" height=\"{HEIGHT}\" \
         viewBox=\"0 0 {WIDTH} {HEIGHT}\" font-family=\"sans-serif\" font-size=\"11\">\
         <rect width=\"100%\" height=\"100%\" fill=\"white\"/>"
    );
    for v in Layout::ticks(l.score) {
        let y = l.y_score(v);
        let _ = write!(
            s,
            "<line x1=\"{x0}\" y1=\"{y:.1}\" x2=\"{x1}\" y2=\"{y:.1}\" stroke=\"{}\"/>\
             <text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\" fill=\"{}\">{}</text>",
            hex(GRID),
            x0 - 6.0,
            y + 4.0,
            hex(SCORE),
            Layout::score_label(v, l.score)
        );
    }
    if let Some(r) = l.accuracy {
        for v in Layout::ticks(r) {
            let _ = write!(
                s,
                "<text x=\"{:.1}\" y=\"{:.1}\" fill=\"{}\">{:.0} %</text>",
                x1 + 6.0,
                Layout::y(r, v) + 4.0,
                hex(ACCURACY),
                v * 100.0
            );
        }
    }
    for v in Layout::ticks(l.photons) {
        let x = l.x(v);
        let _ = write!(
            s,
            "<line x1=\"{x:.1}\" y1=\"{y1}\" x2=\"{x:.1}\" y2=\"{:.1}\" stroke=\"black\"/>\
             <text x=\"{x:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{:.2}</text>",
            y1 + 4.0,
            y1 + 16.0,
            v / l.unit.0
        );
    }
    let _ = write!(
        s,
        "<polyline points=\"{x0},{y0} {x0},{y1} {x1},{y1} {x1},{y0}\" fill=\"none\" stroke=\"black\"/>"
    );
    if let Some(p) = l.refine_from {
        let x = l.x(p);
        let _ = write!(
            s,
            "<line x1=\"{x:.1}\" y1=\"{y0}\" x2=\"{x:.1}\" y2=\"{y1}\" stroke=\"{c}\" stroke-dasharray=\"4 3\"/>\
             <text x=\"{:.1}\" y=\"{:.1}\" fill=\"{c}\">refinement</text>",
            x + 3.0,
            y0 + 12.0,
            c = hex(REFINE)
        );
    }
    let _ = write!(
        s,
        "<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">photons spent ({} photons, all sources)</text>\
         <text x=\"8\" y=\"20\" font-size=\"14\" fill=\"{}\">score</text>",
        x0 + (x1 - x0) / 2.0,
        HEIGHT - 10,
        l.unit.1,
        hex(SCORE)
    );
    if l.accuracy.is_some() {
        let _ = write!(
            s,
            "<text x=\"{}\" y=\"20\" font-size=\"14\" text-anchor=\"end\" fill=\"{}\">pixel accuracy</text>",
            WIDTH - 8,
            hex(ACCURACY)
        );
    }
    for (series, colour, class) in [
        (l.score_polyline(), SCORE, "score"),
        (l.accuracy_polyline(), ACCURACY, "accuracy"),
    ] {
        if series.is_empty() {
            continue;
        }
        let pts: Vec<String> = series
            .iter()
            .map(|(x, y)| format!("{x:.1},{y:.1}"))
            .collect();
        let _ = write!(
            s,
            "<polyline class=\"{class}\" points=\"{}\" fill=\"none\" stroke=\"{c}\" stroke-width=\"2\"/>",
            pts.join(" "),
            c = hex(colour)
        );
        for (x, y) in &series {
            let _ = write!(
                s,
                "<circle cx=\"{x:.1}\" cy=\"{y:.1}\" r=\"3\" fill=\"{}\"/>",
                hex(colour)
            );
        }
    }
    s.push_str("</svg>");
    Some(s)
}

fn put(img: &mut RgbImage, x: f64, y: f64, c: Rgb<u8>) {
    if x >= 0.0 && y >= 0.0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, c);
    }
}

/// A straight line, one pixel wide.
fn line(img: &mut RgbImage, a: (f64, f64), b: (f64, f64), c: Rgb<u8>) {
    let steps = (b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil().max(1.0) as u32;
    for i in 0..=steps {
        let t = f64::from(i) / f64::from(steps);
        put(img, a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t, c);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(
        stage: &str,
        index: u32,
        photons: u64,
        score: f64,
        acc: Option<f64>,
    ) -> ConvergenceReport {
        ConvergenceReport {
            stage: stage.into(),
            index,
            requests: 0,
            renders: 0,
            photons,
            score,
            pixel_accuracy: acc,
        }
    }

    #[test]
    fn the_curve_rises_where_the_score_rises_and_marks_the_refinement() {
        let curve = [
            point("level", 0, 1_000_000, -900.0, Some(0.88)),
            point("level", 1, 3_000_000, -500.0, Some(0.90)),
            point("sweep", 1, 9_000_000, -100.0, Some(0.97)),
        ];
        let svg = svg(&curve).unwrap();
        let l = Layout::new(&curve).unwrap();
        let score = l.score_polyline();
        // Higher scores are drawn higher (smaller y), later photons further right.
        assert!(
            score[0].1 > score[1].1 && score[1].1 > score[2].1,
            "{score:?}"
        );
        assert!(
            score[0].0 < score[1].0 && score[1].0 < score[2].0,
            "{score:?}"
        );
        assert!(l.accuracy_polyline().len() == 3);
        assert!(svg.contains("class=\"score\"") && svg.contains("class=\"accuracy\""));
        assert!(svg.contains("refinement"), "{svg}");
        let img = png(&curve).unwrap();
        assert_eq!((img.width(), img.height()), (WIDTH, HEIGHT));
        // The score's colour is drawn where its last point is.
        let (x, y) = score[2];
        assert_eq!(*img.get_pixel(x as u32, y as u32), SCORE);
    }

    #[test]
    fn no_truth_no_accuracy_and_no_points_no_plot() {
        let curve = [point("level", 0, 10, 0.5, None)];
        let svg = svg(&curve).unwrap();
        assert!(!svg.contains("class=\"accuracy\"") && !svg.contains("refinement"));
        assert!(self::svg(&[]).is_none() && png(&[]).is_none());
        // Ticks close together still read apart.
        let range = (0.99905, 0.99955);
        let labels: Vec<String> = Layout::ticks(range)
            .into_iter()
            .map(|v| Layout::score_label(v, range))
            .collect();
        let distinct: std::collections::BTreeSet<&String> = labels.iter().collect();
        assert_eq!(distinct.len(), 5, "{labels:?}");
    }
}
