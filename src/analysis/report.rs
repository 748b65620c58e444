//! The analysis report: a self-contained HTML page with SVG plots drawn here (plotters), no scripts, no links.

use std::fmt::Write as _;

use plotters::prelude::*;

use super::Analysis;
use super::series::percentile;

const WIDTH: u32 = 900;
const HEIGHT: u32 = 320;
/// Points per plotted line at most (the recording is decimated for drawing only).
const MAX_POINTS: usize = 2500;

type Line<'a> = (&'a str, RGBColor, Vec<(f64, f64)>);

/// One SVG chart of lines; an empty string when there is nothing finite to draw.
fn chart(title: &str, x_label: &str, y_label: &str, lines: &[Line<'_>], points: bool) -> String {
    let all: Vec<(f64, f64)> =
        lines.iter().flat_map(|l| l.2.iter().copied()).filter(|p| p.0.is_finite() && p.1.is_finite()).collect();
    if all.is_empty() {
        return String::new();
    }
    let (mut x0, mut x1) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| (a.0.min(p.0), a.1.max(p.0)));
    let (mut y0, mut y1) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| (a.0.min(p.1), a.1.max(p.1)));
    if x1 <= x0 {
        x1 = x0 + 1.0;
        x0 -= 1.0;
    }
    let pad = 0.05 * (y1 - y0).max(1e-9);
    y0 -= pad;
    y1 += pad;
    let mut svg = String::new();
    let drawn = (|| -> Result<(), Box<dyn std::error::Error + '_>> {
        let root = SVGBackend::with_string(&mut svg, (WIDTH, HEIGHT)).into_drawing_area();
        root.fill(&WHITE)?;
        let mut c = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 16))
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(60)
            .build_cartesian_2d(x0..x1, y0..y1)?;
        c.configure_mesh().x_desc(x_label).y_desc(y_label).light_line_style(WHITE.mix(0.0)).draw()?;
        for (name, color, data) in lines {
            let color = *color;
            let data: Vec<(f64, f64)> = data.iter().copied().filter(|p| p.0.is_finite() && p.1.is_finite()).collect();
            if points {
                c.draw_series(data.iter().map(|&p| Circle::new(p, 3, color.filled())))?
                    .label(*name)
                    .legend(move |(x, y)| Circle::new((x + 10, y), 3, color.filled()));
                c.draw_series(LineSeries::new(data, color.stroke_width(1)))?;
            } else {
                c.draw_series(LineSeries::new(data, color.stroke_width(1)))?
                    .label(*name)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
            }
        }
        c.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw()?;
        root.present()?;
        Ok(())
    })();
    match drawn {
        Ok(()) => svg,
        Err(e) => format!("<p>(plot “{}” could not be drawn: {})</p>", escape(title), escape(&e.to_string())),
    }
}

/// Rows `a..b` of `y` against time, decimated for drawing.
fn decimated(t: &[f64], y: &[f64], a: usize, b: usize) -> Vec<(f64, f64)> {
    let b = b.min(t.len()).min(y.len());
    let step = ((b.saturating_sub(a)) / MAX_POINTS).max(1);
    (a..b).step_by(step).map(|k| (t[k], y[k])).collect()
}

/// Mean of `r` in bins of `x` (20 bins between the 1st and 99th percentile); bins with few samples are left out.
fn binned(x: &[f64], r: &[f64]) -> Vec<(f64, f64)> {
    let (lo, hi) = (percentile(x, 0.01), percentile(x, 0.99));
    if hi.is_nan() || lo.is_nan() || hi <= lo {
        return Vec::new();
    }
    let bins = 20;
    let mut sum = vec![0.0; bins];
    let mut count = vec![0usize; bins];
    for (&xv, &rv) in x.iter().zip(r) {
        if xv.is_finite() && rv.is_finite() && xv >= lo && xv <= hi {
            let i = (((xv - lo) / (hi - lo)) * bins as f64).floor().min(bins as f64 - 1.0) as usize;
            sum[i] += rv;
            count[i] += 1;
        }
    }
    let min_count = (x.len() / 2000).max(5);
    (0..bins)
        .filter(|&i| count[i] >= min_count)
        .map(|i| (lo + (i as f64 + 0.5) * (hi - lo) / bins as f64, sum[i] / count[i] as f64))
        .collect()
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

fn fmt_opt(v: Option<f64>) -> String {
    v.map_or("—".to_string(), |v| format!("{v:.4}"))
}

/// The whole page.
const GRAY: RGBColor = RGBColor(150, 150, 150);
const RED: RGBColor = RGBColor(214, 39, 40);
const BLUE: RGBColor = RGBColor(31, 119, 180);

pub fn html(a: &Analysis) -> String {
    let mut out = String::new();
    head(&mut out, a);
    validation_table(&mut out, a);
    findings(&mut out, a);
    parameters(&mut out, a);
    unexplained(&mut out, a);
    traces(&mut out, a);
    residual_maps(&mut out, a);
    mismatches(&mut out, a);
    candidates(&mut out, a);
    out.push_str("</table></body></html>\n");
    out
}

/// The page's head and the recording's description (with the unknown-load note).
fn head(out: &mut String, a: &Analysis) {
    let _ = write!(
        out,
        "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>hydrolens analysis: {src}</title>\
         <style>body{{font-family:sans-serif;max-width:960px;margin:1em auto;color:#222}}\
         table{{border-collapse:collapse;margin:0.5em 0}}td,th{{border:1px solid #ccc;padding:3px 8px;\
         text-align:left;font-size:90%}}th{{background:#f3f3f3}}.num{{text-align:right}}</style></head><body>\
         <h1>Analysis of {src}</h1>\
         <p>{samples} samples, {family} model family, speed from <code>{speed}</code>. Fitting on the first part, \
         validation from {vf:.2} s (never used for fitting). Free-run simulation of the nominal model{fitted} and of \
         the improved model, driven only by the recording's inputs. Load: {load}.</p>",
        src = escape(&a.recording),
        samples = a.samples,
        family = a.family,
        speed = a.speed_source,
        vf = a.validation_from_s,
        load = a.load,
        fitted = if a.load == "unknown" { "" } else { " (fitted J, B)" }
    );
    if a.load == "unknown" {
        out.push_str(
            "<p><b>The load is unknown</b> (no <code>load_nm</code>): only the flow balance is judged. The measured \
             speed and drive frequency drive a free run of the pressure equation, and the drive model run from the \
             setpoint is compared with the drive frequency read back. The speed is an input, not predicted.</p>",
        );
    }
}

/// The validation errors of the nominal and the improved model.
fn validation_table(out: &mut String, a: &Analysis) {
    let _ = write!(
        out,
        "<h2>Validation error</h2><table><tr><th></th><th>ω NRMSE</th><th>ΔP NRMSE</th><th>torque NRMSE</th>\
         <th>torque relative error</th><th>drive frequency NRMSE</th></tr>"
    );
    let nominal = if a.load == "unknown" { "nominal" } else { "nominal (fitted J, B)" };
    for (name, s) in [(nominal, &a.baseline), ("improved", &a.improved)] {
        let e = &s.validation;
        let _ = write!(
            out,
            "<tr><td>{name}</td><td class=num>{}</td><td class=num>{}</td><td class=num>{}</td>\
             <td class=num>{}</td><td class=num>{}</td></tr>",
            fmt_opt(Some(e.omega_nrmse).filter(|v| v.is_finite())),
            fmt_opt(e.dp_nrmse),
            fmt_opt(e.torque_nrmse),
            fmt_opt(e.torque_relative_error),
            fmt_opt(e.f_drive_nrmse)
        );
    }
    out.push_str("</table>");
}

/// The findings with their evidence, and the validation rule.
fn findings(out: &mut String, a: &Analysis) {
    out.push_str("<h2>Findings</h2>");
    if let Some(m) = &a.model_misfit {
        out.push_str(&format!("<p><strong>{}</strong></p>", escape(&m.explanation)));
    } else if a.findings.is_empty() {
        out.push_str("<p>Nothing is missing: no catalogue effect lowers the validation error by a clear margin.</p>");
    }
    for f in &a.findings {
        let params: Vec<String> = f
            .parameters
            .iter()
            .map(|(k, v)| match f.confidence_intervals.get(k) {
                Some(ci) => format!("{k} = {v:.4} (95 %: {:.4} … {:.4})", ci.low, ci.high),
                None => format!("{k} = {v:.4}"),
            })
            .collect();
        let ev = &f.evidence;
        let _ = write!(
            out,
            "<h3>{}</h3><p>{}</p><p><b>Parameters:</b> {}</p><table><tr><th>ΔBIC (fitting)</th>\
             <th>validation score before → after</th><th>error drop</th><th>residual correlation</th>\
             <th>where it shows</th></tr><tr><td class=num>{:.1}</td><td class=num>{:.5} → {:.5}</td>\
             <td class=num>{:.1} %</td><td class=num>{:.2}</td><td>{}</td></tr></table>",
            escape(&f.effect),
            escape(&f.explanation),
            escape(&params.join(", ")),
            ev.delta_bic,
            ev.validation_score_before,
            ev.validation_score_after,
            100.0 * ev.relative_drop,
            ev.residual_correlation,
            escape(&ev.where_it_shows)
        );
    }
    let _ = write!(out, "<p><b>Validation:</b> {}</p>", escape(&a.validation_rule));
    for f in a.findings.iter().filter(|f| !f.evidence.validated_on.is_empty()) {
        let _ = write!(
            out,
            "<p>{} validated on {} (cross-validation score {} → {}).</p>",
            escape(&f.effect),
            escape(&f.evidence.validated_on),
            fmt_opt(f.evidence.cross_validation_score_before),
            fmt_opt(f.evidence.cross_validation_score_after)
        );
    }
}

/// The improved model's parameters with their confidence intervals.
fn parameters(out: &mut String, a: &Analysis) {
    out.push_str("<h2>Fitted parameters and their confidence intervals</h2>");
    let _ = write!(
        out,
        "<p>{}.</p><table><tr><th>parameter</th><th>value</th><th>95 % low</th><th>95 % high</th></tr>",
        escape(&a.interval_method)
    );
    for (k, v) in &a.improved.parameters {
        let ci = a.improved.confidence_intervals.get(k);
        let _ = write!(
            out,
            "<tr><td>{}</td><td class=num>{v:.5}</td><td class=num>{}</td><td class=num>{}</td></tr>",
            escape(k),
            ci.map_or("not fitted".into(), |c| format!("{:.5}", c.low)),
            ci.map_or("".into(), |c| format!("{:.5}", c.high))
        );
    }
    out.push_str("</table>");
}

/// What the improved model still leaves unexplained, what cannot be told apart, and what is not determined.
fn unexplained(out: &mut String, a: &Analysis) {
    out.push_str("<h2>What the improved model still leaves unexplained</h2>");
    if a.unexplained.is_empty() {
        out.push_str(
            "<p>Nothing: the improved model's residual stays within twice the sensor-noise floor (or above it for \
             less than 1 s in all, and below 5× the floor).</p>",
        );
    } else {
        out.push_str(
            "<table><tr><th>signal</th><th>condition</th><th>share of the recording</th><th>RMS</th>\
             <th>noise floor</th><th>windows (s)</th></tr>",
        );
        for u in &a.unexplained {
            let windows: Vec<String> = u.windows.iter().map(|w| format!("{:.1}–{:.1}", w[0], w[1])).collect();
            let _ = write!(
                out,
                "<tr><td>{}</td><td>{}</td><td class=num>{:.1} %</td><td class=num>{:.3}</td><td class=num>{:.3}</td>\
                 <td>{}</td></tr>",
                escape(&u.signal),
                escape(&u.condition),
                100.0 * u.share,
                u.rms,
                u.noise_floor,
                escape(&windows.join(", "))
            );
        }
        out.push_str("</table>");
    }

    if !a.ambiguities.is_empty() {
        out.push_str("<h2>What this recording cannot tell apart</h2><ul>");
        for amb in &a.ambiguities {
            let _ = write!(out, "<li><b>{}</b>: {}</li>", escape(&amb.effects.join(" / ")), escape(&amb.explanation));
        }
        out.push_str("</ul>");
    }

    if !a.not_identified.is_empty() {
        out.push_str("<h2>What this recording does not determine</h2><ul>");
        for x in &a.not_identified {
            let _ = write!(out, "<li><b>{}</b>: {}</li>", escape(&x.parameters.join(", ")), escape(&x.reason));
        }
        out.push_str("</ul>");
    }
}

/// Measured, nominal and improved traces on the validation segment.
fn traces(out: &mut String, a: &Analysis) {
    let tr = &a.traces;
    let (v, n) = (tr.split, tr.t_s.len());
    out.push_str("<h2>Measured, nominal and improved on the validation segment</h2>");
    out.push_str(&chart(
        "speed",
        "t (s)",
        "ω (rad/s)",
        &[
            ("measured", GRAY, decimated(&tr.t_s, &tr.omega_meas, v, n)),
            ("nominal", RED, decimated(&tr.t_s, &tr.omega_baseline, v, n)),
            ("improved", BLUE, decimated(&tr.t_s, &tr.omega_improved, v, n)),
        ],
        false,
    ));
    out.push_str(&chart(
        tr.effort_name,
        "t (s)",
        tr.effort_name,
        &[
            ("measured", GRAY, decimated(&tr.t_s, &tr.effort_meas, v, n)),
            ("nominal", RED, decimated(&tr.t_s, &tr.effort_baseline, v, n)),
            ("improved", BLUE, decimated(&tr.t_s, &tr.effort_improved, v, n)),
        ],
        false,
    ));

    if !tr.drive_baseline.is_empty() {
        out.push_str(&chart(
            "drive frequency: read back, and the drive model run from the setpoint",
            "t (s)",
            "f (Hz)",
            &[
                ("measured", GRAY, decimated(&tr.t_s, &tr.drive_meas, v, n)),
                ("nominal", RED, decimated(&tr.t_s, &tr.drive_baseline, v, n)),
                ("improved", BLUE, decimated(&tr.t_s, &tr.drive_improved, v, n)),
            ],
            false,
        ));
    }
}

/// The residual maps over the operating point (whole recording).
fn residual_maps(out: &mut String, a: &Analysis) {
    let tr = &a.traces;
    out.push_str(
        "<h2>Residual maps (whole recording)</h2><p>Mean residual (measured − model) in bins of the \
                  operating point: a systematic pattern is physics the model leaves out.</p>",
    );
    let res = |model: &[f64]| -> Vec<f64> { tr.effort_meas.iter().zip(model).map(|(m, p)| m - p).collect() };
    let (rb, ri) = (res(&tr.effort_baseline), res(&tr.effort_improved));
    let label = format!("{} residual", tr.effort_name);
    out.push_str(&chart(
        "residual against speed",
        "ω (rad/s, low-passed)",
        &label,
        &[("nominal", RED, binned(&tr.omega_f, &rb)), ("improved", BLUE, binned(&tr.omega_f, &ri))],
        true,
    ));
    out.push_str(&chart(
        &format!("residual against {}", tr.effort_name),
        tr.effort_name,
        &label,
        &[("nominal", RED, binned(&tr.effort_meas, &rb)), ("improved", BLUE, binned(&tr.effort_meas, &ri))],
        true,
    ));
    let wres = |model: &[f64]| -> Vec<f64> { tr.omega_meas.iter().zip(model).map(|(m, p)| m - p).collect() };
    out.push_str(&chart(
        "speed residual against ΔP / torque",
        tr.effort_name,
        "ω residual (rad/s)",
        &[
            ("nominal", RED, binned(&tr.effort_meas, &wres(&tr.omega_baseline))),
            ("improved", BLUE, binned(&tr.effort_meas, &wres(&tr.omega_improved))),
        ],
        true,
    ));
}

/// The windows where the nominal model misses.
fn mismatches(out: &mut String, a: &Analysis) {
    out.push_str("<h2>Where the nominal model misses</h2>");
    if a.mismatches.is_empty() {
        out.push_str("<p>No window stands out from the rest.</p>");
    } else {
        out.push_str("<table><tr><th>from (s)</th><th>to (s)</th><th>signal</th><th>conditions</th><th>RMS</th></tr>");
        for m in &a.mismatches {
            let _ = write!(
                out,
                "<tr><td class=num>{:.2}</td><td class=num>{:.2}</td><td>{}</td><td>{}</td><td class=num>{:.3}</td></tr>",
                m.t_start_s,
                m.t_end_s,
                escape(&m.signal),
                escape(&m.condition),
                m.rms
            );
        }
        out.push_str("</table>");
    }
}

/// Every candidate tried, with its scores.
fn candidates(out: &mut String, a: &Analysis) {
    out.push_str(
        "<h2>Every candidate tried</h2><table><tr><th>round</th><th>effect</th><th>validation score</th>\
                  <th>ΔBIC</th><th>cross-validation score</th><th>regime drop</th><th>kept</th></tr>",
    );
    for c in &a.candidates {
        let _ = write!(
            out,
            "<tr><td>{}</td><td>{}</td><td class=num>{}</td><td class=num>{}</td><td class=num>{}</td>\
             <td class=num>{}</td><td>{}</td></tr>",
            c.round,
            escape(&c.effect),
            c.validation_score.map_or("not fittable".into(), |v| format!("{v:.5}")),
            c.delta_bic.map_or("—".into(), |v| format!("{v:.1}")),
            c.cross_validation_score.map_or("—".into(), |v| format!("{v:.5}")),
            c.regime_drop.map_or("—".into(), |v| format!("{:.1} %", 100.0 * v)),
            if c.kept { "yes" } else { "" }
        );
    }
}
