//! Hand-written SVG line charts (ROC and precision–recall curves). No dependency.
//!
//! * [`line_chart`]: a few series (one per transformation class), each in its own colour, on
//!   [0, 1]², with a legend beside the plot.
//! * [`overview_chart`]: many series (one per configuration): the default configuration and the
//!   best few by a score are drawn in colour and named in the legend, every other one as a thin
//!   grey line summarised by one legend entry; optionally a logarithmic x axis (false-positive
//!   rate from 10⁻³), where the ROC curves of good configurations differ.
//!
//! The legend never runs off the canvas: long names are shortened with an ellipsis and, past the
//! rows that fit, the remaining series are counted in a last "+ N more" row.

use std::fmt::Write;

/// Ten well-separated colours (Tableau 10); the default series of an overview is black.
const PALETTE: [&str; 10] = [
    "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf",
    "#bcbd22", "#7f7f7f",
];

/// Escapes text for SVG/XML.
pub fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// Shortens `s` to at most `max` characters, ending in "…" when cut.
fn ellipsize(s: &str, max: usize) -> String {
    if s.chars().count() <= max {
        s.to_string()
    } else {
        let mut t: String = s.chars().take(max.saturating_sub(1)).collect();
        t.push('…');
        t
    }
}

/// How the x axis maps data to the plot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum XAxis {
    /// Linear on [0, 1].
    Linear,
    /// log10 on [min, 1]; values below `min` (0 included) are drawn at `min`.
    Log {
        /// Left end of the axis (e.g. 1e-3).
        min: f64,
    },
}

impl XAxis {
    /// Position in [0, 1] of the data value `x`.
    fn unit(self, x: f64) -> f64 {
        match self {
            XAxis::Linear => x.clamp(0.0, 1.0),
            XAxis::Log { min } => {
                let lo = min.log10();
                ((x.max(min).log10() - lo) / -lo).clamp(0.0, 1.0)
            }
        }
    }
    fn ticks(self) -> Vec<(f64, String)> {
        match self {
            XAxis::Linear => (0..=5)
                .map(|i| (i as f64 / 5.0, format!("{:.1}", i as f64 / 5.0)))
                .collect(),
            XAxis::Log { min } => {
                let mut out = Vec::new();
                let mut e = min.log10().ceil() as i32;
                while e <= 0 {
                    let v = 10f64.powi(e);
                    let label = if e >= -3 {
                        format!("{v}")
                    } else {
                        format!("1e{e}")
                    };
                    out.push((v, label));
                    e += 1;
                }
                out
            }
        }
    }
}

/// A series to draw.
struct Line<'a> {
    label: String,
    points: &'a [(f64, f64)],
    color: &'a str,
    width: f64,
    dash: bool,
    /// Shown in the legend (grey background lines are summarised instead).
    in_legend: bool,
}

const W: f64 = 900.0;
const H: f64 = 520.0;
const LEFT: f64 = 60.0;
const RIGHT: f64 = 330.0;
const TOP: f64 = 40.0;
const BOTTOM: f64 = 50.0;
const LEGEND_ROW: f64 = 17.0;
/// Characters of a legend label that fit in the legend column at font size 11.
const LEGEND_CHARS: usize = 46;

#[allow(clippy::too_many_arguments)]
fn draw(
    title: &str,
    xlabel: &str,
    ylabel: &str,
    lines: &[Line],
    summary: Option<(String, &str)>,
    diagonal: bool,
    x_axis: XAxis,
) -> String {
    let pw = W - LEFT - RIGHT;
    let ph = H - TOP - BOTTOM;
    let sx = |x: f64| LEFT + x_axis.unit(x) * pw;
    let sy = |y: f64| TOP + (1.0 - y.clamp(0.0, 1.0)) * ph;
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}" font-family="DejaVu Sans, Verdana, sans-serif" font-size="12">"#
    );
    let _ = writeln!(s, r#"<rect width="{W}" height="{H}" fill="white"/>"#);
    let _ = writeln!(
        s,
        r#"<text x="{}" y="24" text-anchor="middle" font-size="15">{}</text>"#,
        LEFT + pw / 2.0,
        xml_escape(title)
    );
    for (v, label) in x_axis.ticks() {
        let _ = writeln!(
            s,
            r##"<line x1="{x}" y1="{y0}" x2="{x}" y2="{y1}" stroke="#e2e2e2"/><text x="{x}" y="{ty}" text-anchor="middle">{label}</text>"##,
            x = sx(v),
            y0 = sy(0.0),
            y1 = sy(1.0),
            ty = sy(0.0) + 16.0
        );
    }
    for i in 0..=5 {
        let v = i as f64 / 5.0;
        let _ = writeln!(
            s,
            r##"<line x1="{x0}" y1="{y}" x2="{x1}" y2="{y}" stroke="#e2e2e2"/><text x="{tx}" y="{ty}" text-anchor="end">{v:.1}</text>"##,
            x0 = LEFT,
            x1 = LEFT + pw,
            y = sy(v),
            tx = LEFT - 6.0,
            ty = sy(v) + 4.0
        );
    }
    let _ = writeln!(
        s,
        r#"<text x="{}" y="{}" text-anchor="middle">{}</text>"#,
        LEFT + pw / 2.0,
        H - 12.0,
        xml_escape(xlabel)
    );
    let _ = writeln!(
        s,
        r#"<text x="16" y="{}" text-anchor="middle" transform="rotate(-90 16 {})">{}</text>"#,
        TOP + ph / 2.0,
        TOP + ph / 2.0,
        xml_escape(ylabel)
    );
    if diagonal {
        // y = x, a curve on a log axis.
        let mut p = String::new();
        for i in 0..=60 {
            let x = match x_axis {
                XAxis::Linear => i as f64 / 60.0,
                XAxis::Log { min } => 10f64.powf(min.log10() * (1.0 - i as f64 / 60.0)),
            };
            let _ = write!(p, "{:.2},{:.2} ", sx(x), sy(x));
        }
        let _ = writeln!(
            s,
            r##"<polyline fill="none" stroke="#999" stroke-dasharray="4 4" points="{}"/>"##,
            p.trim_end()
        );
    }
    // Background lines first, highlighted ones on top (the legend's first entry drawn last).
    for l in lines.iter().rev() {
        let mut p = String::new();
        for &(x, y) in l.points {
            if x.is_finite() && y.is_finite() {
                let _ = write!(p, "{:.2},{:.2} ", sx(x), sy(y));
            }
        }
        let dash = if l.dash {
            r#" stroke-dasharray="6 3""#
        } else {
            ""
        };
        let _ = writeln!(
            s,
            r#"<polyline fill="none" stroke="{}" stroke-width="{}"{dash} stroke-linejoin="round" points="{}"/>"#,
            l.color,
            l.width,
            p.trim_end()
        );
    }
    let _ = writeln!(
        s,
        r#"<rect x="{LEFT}" y="{TOP}" width="{pw}" height="{ph}" fill="none" stroke="black"/>"#
    );
    // Legend: the rows that fit, then "+ N more" and the summary row.
    let lx = LEFT + pw + 14.0;
    let shown: Vec<&Line> = lines.iter().filter(|l| l.in_legend).collect();
    let reserved = 1 + usize::from(summary.is_some());
    let max_rows = ((H - TOP - 10.0) / LEGEND_ROW) as usize;
    let fit = if shown.len() + reserved - 1 > max_rows {
        max_rows - reserved
    } else {
        shown.len()
    };
    let mut row = 0usize;
    let mut legend_row = |s: &mut String, color: &str, width: f64, dash: bool, text: &str| {
        let ly = TOP + 10.0 + LEGEND_ROW * row as f64;
        let dash = if dash {
            r#" stroke-dasharray="6 3""#
        } else {
            ""
        };
        let _ = writeln!(
            s,
            r#"<line x1="{lx}" y1="{ly}" x2="{}" y2="{ly}" stroke="{color}" stroke-width="{}"{dash}/><text x="{}" y="{}" font-size="11">{}</text>"#,
            lx + 20.0,
            width.max(2.0),
            lx + 26.0,
            ly + 4.0,
            xml_escape(&ellipsize(text, LEGEND_CHARS))
        );
        row += 1;
    };
    for l in shown.iter().take(fit) {
        legend_row(&mut s, l.color, l.width, l.dash, &l.label);
    }
    if shown.len() > fit {
        legend_row(
            &mut s,
            "#bbb",
            1.0,
            false,
            &format!("+ {} more", shown.len() - fit),
        );
    }
    if let Some((text, color)) = summary {
        legend_row(&mut s, color, 1.0, false, &text);
    }
    s.push_str("</svg>\n");
    s
}

/// An SVG chart of `series` (name, points in `[0, 1]²`) with the given title and axis labels.
/// `diagonal` draws the chance line y = x (for ROC curves). Each series has its own colour
/// (dashed after the tenth); the legend lists as many as fit.
pub fn line_chart(
    title: &str,
    xlabel: &str,
    ylabel: &str,
    series: &[(String, Vec<(f64, f64)>)],
    diagonal: bool,
) -> String {
    let lines: Vec<Line> = series
        .iter()
        .enumerate()
        .map(|(i, (name, pts))| Line {
            label: name.clone(),
            points: pts,
            color: PALETTE[i % PALETTE.len()],
            width: 1.6,
            dash: i >= PALETTE.len(),
            in_legend: true,
        })
        .collect();
    draw(title, xlabel, ylabel, &lines, None, diagonal, XAxis::Linear)
}

/// One configuration's curve on an [`overview_chart`].
#[derive(Debug, Clone)]
pub struct Series {
    /// Configuration name.
    pub name: String,
    /// Curve points in [0, 1]².
    pub points: Vec<(f64, f64)>,
    /// What "best" is ranked by (higher is better, e.g. mAP); `None` is never among the best.
    pub score: Option<f64>,
}

/// Options of [`overview_chart`].
#[derive(Debug, Clone)]
pub struct Overview<'a> {
    /// Name of the series drawn in black and listed first (the product default), if present.
    pub default: Option<&'a str>,
    /// How many of the best other series (by score) to draw in colour.
    pub best: usize,
    /// Label of the score in the legend, e.g. "mAP" (scores are printed ×100 with one decimal).
    pub score_label: &'a str,
    /// The x axis.
    pub x_axis: XAxis,
    /// Draw the chance line y = x.
    pub diagonal: bool,
}

/// Indices of the series an overview highlights: the default first (if present), then the
/// `best` highest scores among the others, best first (ties by position).
pub fn highlighted(series: &[Series], default: Option<&str>, best: usize) -> Vec<usize> {
    let def = default.and_then(|d| series.iter().position(|s| s.name == d));
    let mut others: Vec<usize> = (0..series.len())
        .filter(|&i| Some(i) != def && series[i].score.is_some_and(f64::is_finite))
        .collect();
    others.sort_by(|&a, &b| {
        let (sa, sb) = (
            series[a].score.unwrap_or(0.0),
            series[b].score.unwrap_or(0.0),
        );
        sb.total_cmp(&sa).then(a.cmp(&b))
    });
    def.into_iter()
        .chain(others.into_iter().take(best))
        .collect()
}

/// A chart of many configurations: the default and the `best` few in colour with a legend,
/// every other configuration as a thin grey line counted in one legend row.
pub fn overview_chart(
    title: &str,
    xlabel: &str,
    ylabel: &str,
    series: &[Series],
    opts: &Overview,
) -> String {
    let hi = highlighted(series, opts.default, opts.best);
    let label = |s: &Series| match s.score {
        Some(v) if v.is_finite() => format!("{} ({} {:.1})", s.name, opts.score_label, 100.0 * v),
        _ => s.name.clone(),
    };
    let mut lines: Vec<Line> = Vec::with_capacity(series.len());
    let mut best_i = 0usize;
    for &i in &hi {
        let is_default = opts.default == Some(series[i].name.as_str());
        let (color, text) = if is_default {
            ("#000000", format!("{} — default", label(&series[i])))
        } else {
            best_i += 1;
            (
                PALETTE[(best_i - 1) % PALETTE.len()],
                format!("{best_i}. {}", label(&series[i])),
            )
        };
        lines.push(Line {
            label: text,
            points: &series[i].points,
            color,
            width: if is_default { 2.6 } else { 1.8 },
            dash: false,
            in_legend: true,
        });
    }
    let rest: Vec<usize> = (0..series.len()).filter(|i| !hi.contains(i)).collect();
    for &i in &rest {
        lines.push(Line {
            label: series[i].name.clone(),
            points: &series[i].points,
            color: "#d4d4d4",
            width: 0.7,
            dash: false,
            in_legend: false,
        });
    }
    let summary =
        (!rest.is_empty()).then(|| (format!("{} other configurations", rest.len()), "#c8c8c8"));
    draw(
        title,
        xlabel,
        ylabel,
        &lines,
        summary,
        opts.diagonal,
        opts.x_axis,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn series(n: usize) -> Vec<Series> {
        (0..n)
            .map(|i| Series {
                name: format!("config-{i:03}-with-a-rather-long-name[t=0.016..0.1]"),
                points: (0..=10)
                    .map(|k| {
                        let x = k as f64 / 10.0;
                        (x, x.powf(0.2 + i as f64 / n as f64))
                    })
                    .collect(),
                score: Some(i as f64 / n as f64),
            })
            .collect()
    }

    fn legend_texts(svg: &str) -> Vec<String> {
        svg.lines()
            .filter(|l| l.contains(r#"font-size="11""#))
            .map(|l| {
                let a = l.rfind("\">").unwrap() + 2;
                let b = l.rfind("</text>").unwrap();
                l[a..b].to_string()
            })
            .collect()
    }

    #[test]
    fn highlighted_is_default_then_best() {
        let mut s = series(20);
        s[3].name = "default".into();
        s[7].score = None;
        assert_eq!(highlighted(&s, Some("default"), 4), vec![3, 19, 18, 17, 16]);
        assert_eq!(highlighted(&s, None, 2), vec![19, 18]);
        assert_eq!(highlighted(&s, Some("absent"), 1), vec![19]);
    }

    #[test]
    fn overview_legend_fits_and_names_the_highlighted() {
        let mut s = series(155);
        s[154].name = "default".into();
        let svg = overview_chart(
            "Mean ROC",
            "false positive rate",
            "true positive rate",
            &s,
            &Overview {
                default: Some("default"),
                best: 5,
                score_label: "mAP",
                x_axis: XAxis::Log { min: 1e-3 },
                diagonal: true,
            },
        );
        let legend = legend_texts(&svg);
        assert_eq!(legend.len(), 7, "{legend:?}");
        assert!(legend[0].starts_with("default (mAP 99.4)"), "{}", legend[0]);
        assert!(legend[1].starts_with("1. config-153"), "{}", legend[1]);
        assert_eq!(legend[6], "149 other configurations");
        for t in &legend {
            assert!(t.chars().count() <= LEGEND_CHARS, "{t}");
        }
        // Every series is drawn: 155 curves + the diagonal.
        assert_eq!(svg.matches("<polyline").count(), 156);
        // Log axis ticks.
        for t in [">0.001<", ">0.01<", ">0.1<", ">1<"] {
            assert!(svg.contains(t), "tick {t}");
        }
    }

    #[test]
    fn line_chart_legend_never_overflows() {
        let s: Vec<(String, Vec<(f64, f64)>)> = series(155)
            .into_iter()
            .map(|s| (s.name, s.points))
            .collect();
        let svg = line_chart("t", "x", "y", &s, false);
        let legend = legend_texts(&svg);
        let max_rows = ((H - TOP - 10.0) / LEGEND_ROW) as usize;
        assert_eq!(legend.len(), max_rows);
        assert_eq!(
            legend.last().unwrap(),
            &format!("+ {} more", 155 - (max_rows - 1))
        );
        // Legend rows stay inside the canvas.
        let last_y = TOP + 10.0 + LEGEND_ROW * (max_rows - 1) as f64 + 4.0;
        assert!(last_y < H);
    }

    #[test]
    fn log_axis_maps_decades_evenly() {
        let a = XAxis::Log { min: 1e-3 };
        assert!((a.unit(1e-3) - 0.0).abs() < 1e-12);
        assert!((a.unit(1e-2) - 1.0 / 3.0).abs() < 1e-12);
        assert!((a.unit(1.0) - 1.0).abs() < 1e-12);
        assert_eq!(a.unit(0.0), 0.0);
    }
}
