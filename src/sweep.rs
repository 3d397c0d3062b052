//! Measurement reports: `canopy npp` (nodes per pixel as resolution grows, 004 §5.2) and
//! `canopy eval` (error against time for each integrator). Both write CSV, an SVG plot
//! (plotters) and, for `eval`, a Markdown table with c = RMSE·√seconds per row.

use crate::image::{write_atomically, Image};
use crate::integrator::{cone::ConeSettings, pbgi::PbgiSettings, Kind, Settings};
use crate::metrics::{error, Metric};
use crate::render::{render, RenderOptions, RenderStats};
use anyhow::{bail, Context, Result};
use plotters::prelude::*;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// One plotted line.
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// A log-log line plot as SVG.
pub fn plot_loglog(path: &Path, title: &str, x: &str, y: &str, series: &[Series]) -> Result<()> {
    let pts: Vec<(f64, f64)> = series
        .iter()
        .flat_map(|s| s.points.iter().copied())
        .filter(|(a, b)| *a > 0.0 && *b > 0.0 && a.is_finite() && b.is_finite())
        .collect();
    if pts.is_empty() {
        bail!("{}: nothing to plot", path.display());
    }
    let (x0, x1) = pts
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let (y0, y1) = pts
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (720, 480)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow::anyhow!("{e}"))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(
                (x0 / 1.5..x1 * 1.5).log_scale(),
                (y0 / 1.5..y1 * 1.5).log_scale(),
            )
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        chart
            .configure_mesh()
            .x_desc(x)
            .y_desc(y)
            .draw()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        for (i, s) in series.iter().enumerate() {
            let colour = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(s.points.clone(), colour.stroke_width(2)))
                .map_err(|e| anyhow::anyhow!("{e}"))?
                .label(s.name.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], colour));
            chart
                .draw_series(s.points.iter().map(|&p| Circle::new(p, 3, colour.filled())))
                .map_err(|e| anyhow::anyhow!("{e}"))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        root.present().map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    write_atomically(path, |tmp| Ok(std::fs::write(tmp, svg)?))
}

fn write_text(path: &Path, text: &str) -> Result<()> {
    write_atomically(path, |tmp| Ok(std::fs::write(tmp, text)?))
}

/// Settings shared by the sweeps: everything of a render (archive included) but the
/// output, size and time, and the cone integrator's settings for sweeps that run it.
#[derive(Clone)]
pub struct SweepOptions {
    pub out_dir: PathBuf,
    pub base: RenderOptions,
    pub cone: ConeSettings,
    pub pbgi: PbgiSettings,
}

impl SweepOptions {
    fn settings(&self, kind: Kind) -> Settings {
        match kind {
            Kind::Path => Settings::Path,
            Kind::Cone => Settings::Cone(self.cone.clone()),
            Kind::Pbgi => Settings::Pbgi(self.pbgi.clone()),
        }
    }
}

fn render_into(
    o: &SweepOptions,
    name: &str,
    f: impl FnOnce(&mut RenderOptions),
) -> Result<(Image, RenderStats)> {
    let mut r = o.base.clone();
    r.output = o.out_dir.join(format!("{name}.exr"));
    r.stats = Some(o.out_dir.join(format!("{name}.json")));
    f(&mut r);
    render(&r)
}

#[derive(Debug, serde::Serialize)]
pub struct NppRow {
    pub integrator: Kind,
    pub width: u32,
    pub height: u32,
    pub pixels: u64,
    pub spp: u32,
    /// `Film::noise` at this spp.
    pub noise: f64,
    pub unique_nodes: u64,
    pub nodes_per_pixel: f64,
    /// True on the row where the resolution's render stopped (the noise target or --spp).
    pub last: bool,
    pub pages_touched: u64,
    pub resident_bytes_peak: u64,
    pub seconds: f64,
}

/// `canopy npp`: for each integrator and each height in `resolutions` (width from the
/// camera's aspect), one render that doubles its spp until the image's relative noise is
/// at most `noise` (at most `max_spp`), so that every resolution is counted at equal noise
/// as 004 §5.2 asks; a row per power of two shows how the count grows with spp.
pub fn npp(
    o: &SweepOptions,
    integrators: &[Kind],
    resolutions: &[u32],
    noise: f64,
    max_spp: u32,
) -> Result<Vec<NppRow>> {
    std::fs::create_dir_all(&o.out_dir)
        .with_context(|| format!("{}: cannot create", o.out_dir.display()))?;
    let mut rows = Vec::new();
    for &i in integrators {
        for &h in resolutions {
            let name = format!("npp_{i:?}_{h}").to_lowercase();
            let (_, s) = render_into(o, &name, |r| {
                r.integrator = o.settings(i);
                r.height = Some(h);
                r.width = None;
                r.spp = max_spp;
                r.noise = Some(noise);
            })?;
            let pixels = s.width as u64 * s.height as u64;
            for (k, c) in s.growth.iter().enumerate() {
                rows.push(NppRow {
                    integrator: i,
                    width: s.width,
                    height: s.height,
                    pixels,
                    spp: c.spp,
                    noise: c.noise,
                    unique_nodes: c.unique_nodes,
                    nodes_per_pixel: c.unique_nodes as f64 / pixels as f64,
                    last: k + 1 == s.growth.len(),
                    pages_touched: s.cache.pages_touched,
                    resident_bytes_peak: s.cache.resident_bytes_peak,
                    seconds: c.seconds,
                });
            }
        }
    }
    write_npp(o, integrators, &rows)?;
    Ok(rows)
}

/// npp.csv (every row) and npp.svg (used nodes against pixels at the stopping rows, as
/// 004 Fig. 14 plots them, beside one and 100 nodes per pixel).
fn write_npp(o: &SweepOptions, integrators: &[Kind], rows: &[NppRow]) -> Result<()> {
    let mut csv = String::from("integrator,width,height,pixels,spp,noise,unique_nodes,nodes_per_pixel,last,pages_touched,resident_bytes_peak,seconds\n");
    for r in rows {
        writeln!(
            csv,
            "{:?},{},{},{},{},{:.5},{},{:.3},{},{},{},{:.3}",
            r.integrator,
            r.width,
            r.height,
            r.pixels,
            r.spp,
            r.noise,
            r.unique_nodes,
            r.nodes_per_pixel,
            r.last,
            r.pages_touched,
            r.resident_bytes_peak,
            r.seconds
        )?;
    }
    write_text(&o.out_dir.join("npp.csv"), &csv)?;
    let last: Vec<&NppRow> = rows.iter().filter(|r| r.last).collect();
    let mut series: Vec<Series> = integrators
        .iter()
        .map(|&i| Series {
            name: format!("{i:?}: used nodes at equal noise"),
            points: last
                .iter()
                .filter(|r| r.integrator == i)
                .map(|r| (r.pixels as f64, r.unique_nodes as f64))
                .collect(),
        })
        .collect();
    for per_pixel in [1.0, 100.0] {
        series.push(Series {
            name: format!("{per_pixel} per pixel"),
            points: last
                .iter()
                .map(|r| (r.pixels as f64, per_pixel * r.pixels as f64))
                .collect(),
        });
    }
    plot_loglog(
        &o.out_dir.join("npp.svg"),
        "Used nodes against pixels (004 Fig. 14)",
        "pixels",
        "nodes",
        &series,
    )
}

impl NppRow {
    pub const HEADER: &str =
        "integrator     pixels   spp   noise  unique nodes  nodes/pixel  pages  resident MiB  seconds";
}

impl std::fmt::Display for NppRow {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(
            f,
            "{:<10} {:>10}  {:>4}  {:>6.4}  {:>12}  {:>11.2}  {:>5}  {:>12.1}  {:>7.2}{}",
            format!("{:?}", self.integrator),
            self.pixels,
            self.spp,
            self.noise,
            self.unique_nodes,
            self.nodes_per_pixel,
            self.pages_touched,
            self.resident_bytes_peak as f64 / 1048576.0,
            self.seconds,
            if self.last { "  <- stopped" } else { "" }
        )
    }
}

impl std::fmt::Display for EvalRow {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(
            f,
            "{:?} {:>6.1}s: {} spp, RMSE {:.4e}, c {:.4e}",
            self.integrator, self.seconds, self.spp, self.rmse, self.c
        )
    }
}

#[derive(Debug, serde::Serialize)]
pub struct EvalRow {
    pub integrator: Kind,
    pub budget_seconds: f64,
    pub seconds: f64,
    pub spp: u32,
    pub rmse: f64,
    /// RMSE·√seconds: lower is better; (c₁/c₂)² is the equal-error speed ratio.
    pub c: f64,
}

/// `canopy eval`: each integrator at each time budget against a reference.
pub fn eval(
    o: &SweepOptions,
    reference: &Path,
    integrators: &[Kind],
    times: &[Duration],
) -> Result<Vec<EvalRow>> {
    std::fs::create_dir_all(&o.out_dir)
        .with_context(|| format!("{}: cannot create", o.out_dir.display()))?;
    let r = Image::read_exr(reference)?;
    let mut rows = Vec::new();
    for &i in integrators {
        for &t in times {
            let name = format!("eval_{i:?}_{}s", t.as_secs_f64()).to_lowercase();
            let (img, s) = render_into(o, &name, |ro| {
                ro.integrator = o.settings(i);
                ro.time = Some(t);
                // As many samples as the time allows.
                ro.spp = u32::MAX - 1;
                ro.width = Some(r.width);
                ro.height = Some(r.height);
            })?;
            let rmse = error(&img, &r, Metric::Rmse)?;
            rows.push(EvalRow {
                integrator: i,
                budget_seconds: t.as_secs_f64(),
                seconds: s.seconds.render,
                spp: s.spp,
                rmse,
                c: rmse * s.seconds.render.sqrt(),
            });
        }
    }
    let mut csv = String::from("integrator,budget_seconds,seconds,spp,rmse,c\n");
    let mut md = String::from("| integrator | budget | seconds | spp | RMSE | c = RMSE·√s |\n| --- | --- | --- | --- | --- | --- |\n");
    for r in &rows {
        writeln!(
            csv,
            "{:?},{},{:.3},{},{:.6e},{:.6e}",
            r.integrator, r.budget_seconds, r.seconds, r.spp, r.rmse, r.c
        )?;
        writeln!(
            md,
            "| {:?} | {}s | {:.2} | {} | {:.4e} | {:.4e} |",
            r.integrator, r.budget_seconds, r.seconds, r.spp, r.rmse, r.c
        )?;
    }
    for line in time_to_match(&rows) {
        md.push('\n');
        md.push_str(&line);
        md.push('\n');
    }
    write_text(&o.out_dir.join("eval.csv"), &csv)?;
    write_text(&o.out_dir.join("eval.md"), &md)?;
    let series: Vec<Series> = integrators
        .iter()
        .map(|&i| Series {
            name: format!("{i:?}"),
            points: rows
                .iter()
                .filter(|r| r.integrator == i)
                .map(|r| (r.seconds, r.rmse))
                .collect(),
        })
        .collect();
    plot_loglog(
        &o.out_dir.join("eval.svg"),
        "RMSE against render time",
        "seconds",
        "RMSE",
        &series,
    )?;
    Ok(rows)
}

/// For each approximate integrator of the rows, how long it needs to reach the path
/// tracer's error at its longest budget, interpolating its error curve in log-log (or
/// extrapolating along 1/√t).
pub fn time_to_match(rows: &[EvalRow]) -> Vec<String> {
    let Some(target) = rows
        .iter()
        .filter(|r| r.integrator == Kind::Path)
        .max_by(|a, b| a.seconds.total_cmp(&b.seconds))
    else {
        return Vec::new();
    };
    let mut kinds: Vec<Kind> = Vec::new();
    for r in rows {
        if r.integrator != Kind::Path && !kinds.contains(&r.integrator) {
            kinds.push(r.integrator);
        }
    }
    kinds
        .into_iter()
        .filter_map(|kind| {
            let mut own: Vec<&EvalRow> = rows.iter().filter(|r| r.integrator == kind).collect();
            own.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
            let t = seconds_to_reach(&own, target.rmse)?;
            Some(format!(
                "The {} integrator reaches the path tracer's {:.1}-second RMSE ({:.4e}) in about {:.2} s: {:.2}× faster.",
                format!("{kind:?}").to_lowercase(),
                target.seconds,
                target.rmse,
                t,
                target.seconds / t
            ))
        })
        .collect()
}

/// When a series sorted by time reaches `rmse`.
fn seconds_to_reach(series: &[&EvalRow], rmse: f64) -> Option<f64> {
    let first = series.first()?;
    if first.rmse <= rmse {
        // Already below at the shortest budget: extrapolate back along 1/√t.
        return Some(first.seconds * (first.rmse / rmse).powi(2));
    }
    Some(match series.windows(2).find(|w| w[1].rmse <= rmse) {
        Some(w) => {
            let (l0, l1) = (w[0].seconds.ln(), w[1].seconds.ln());
            let (e0, e1) = (w[0].rmse.ln(), w[1].rmse.ln());
            (l0 + (rmse.ln() - e0) * (l1 - l0) / (e1 - e0)).exp()
        }
        None => {
            let last = series.last()?;
            last.seconds * (last.rmse / rmse).powi(2)
        }
    })
}
