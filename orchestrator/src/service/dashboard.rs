//! The dashboard's pages, rendered on the server: the job list, a job's page (kept live by a
//! little plain JavaScript that follows `/jobs/ID/events`, the same numbered events as `mscale
//! watch`), the newest stress profile as inline-able SVG, and the run directory's files as
//! links. No script or style is fetched from anywhere: everything is in the page.

use super::auth::Caller;
use super::error::JobError;
use super::fetch::run_files;
use super::shared::{Core, lock};
use super::store::JobRecord;
use mscale_proto::orchestrator::v1 as pb;
use std::fmt::Write;

/// `s` escaped for HTML text and attribute values.
pub(crate) fn esc(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

const STYLE: &str = "body{font:14px system-ui,sans-serif;margin:1.5em;color:#222}table{border-collapse:collapse}\
td,th{border:1px solid #ccc;padding:3px 8px;text-align:left}th{background:#f3f3f3}\
.state{font-weight:bold}.completed{color:#176d17}.failed{color:#b00}.cancelled{color:#a60}.running{color:#1456b8}\
progress{width:28em;height:1.2em}dl{display:grid;grid-template-columns:max-content auto;gap:2px 12px}dt{color:#666}\
#log{font:12px monospace;max-height:12em;overflow:auto;background:#fafafa;border:1px solid #ddd;padding:4px}";

fn page(title: &str, body: &str) -> String {
    format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{}</title><style>{STYLE}</style></head><body>{body}</body></html>\n",
        esc(title)
    )
}

fn percent(j: &JobRecord) -> f64 {
    if j.steps > 0 { 100.0 * j.step.min(j.steps) as f64 / j.steps as f64 } else { 0.0 }
}

/// `GET /`: every job, newest first, with state and progress.
pub(crate) fn job_list(core: &Core, caller: &Caller) -> Result<String, JobError> {
    let mut jobs = core.jobs_of(caller)?;
    jobs.sort_by(|a, b| b.submitted.cmp(&a.submitted).then(b.id.cmp(&a.id)));
    let mut rows = String::new();
    for j in &jobs {
        let p = percent(j);
        let _ = write!(
            rows,
            "<tr id=\"job-{id}\" data-state=\"{st}\"><td><a href=\"/jobs/{id}\">{id}</a></td><td>{scene}</td><td class=\"owner\">{owner}</td><td class=\"state {st}\">{st}</td>\
             <td><progress max=\"100\" value=\"{p:.1}\"></progress> {p:.1} % ({step}/{steps})</td><td>{sub}</td><td>{err}</td></tr>",
            id = esc(&j.id),
            scene = esc(&j.scene),
            owner = esc(&j.owner),
            st = j.state.as_str(),
            step = j.step,
            steps = j.steps,
            sub = utc(j.submitted),
            err = esc(&j.error),
        );
    }
    let body = format!(
        "<h1>mscale jobs</h1><p>{} jobs; <a href=\"/metrics\">metrics</a></p><table id=\"jobs\"><tr><th>job</th><th>scene</th><th>owner</th><th>state</th>\
         <th>progress</th><th>submitted (UTC)</th><th>note</th></tr>{rows}</table>\
         <script>setTimeout(()=>location.reload(),5000)</script>",
        jobs.len()
    );
    Ok(page("mscale jobs", &body))
}

fn utc(unix: i64) -> String {
    if unix <= 0 {
        return String::new();
    }
    time::OffsetDateTime::from_unix_timestamp(unix)
        .map(|t| format!("{:04}-{:02}-{:02} {:02}:{:02}:{:02}", t.year(), t.month() as u8, t.day(), t.hour(), t.minute(), t.second()))
        .unwrap_or_default()
}

/// An event as the page's script reads it.
pub(crate) fn event_json(ev: &pb::JobEvent) -> serde_json::Value {
    let state = pb::JobState::try_from(ev.state).map_or("unspecified", |s| match s {
        pb::JobState::Queued => "queued",
        pb::JobState::Running => "running",
        pb::JobState::Completed => "completed",
        pb::JobState::Failed => "failed",
        pb::JobState::Cancelled => "cancelled",
        pb::JobState::Unspecified => "unspecified",
    });
    let kind = pb::JobEventKind::try_from(ev.kind).map_or("unspecified", |k| k.as_str_name()).trim_start_matches("JOB_EVENT_KIND_");
    let workers: Vec<serde_json::Value> = ev
        .workers
        .iter()
        .map(|w| {
            serde_json::json!({
                "id": w.worker_id, "address": w.address,
                "state": pb::WorkerState::try_from(w.state).map_or("unspecified", |s| s.as_str_name()).trim_start_matches("WORKER_STATE_").to_lowercase(),
                "boxes": w.boxes, "advertised": w.advertised_atom_steps_per_s, "measured": w.measured_atom_steps_per_s,
            })
        })
        .collect();
    let finite = |x: f64| if x.is_finite() { serde_json::json!(x) } else { serde_json::Value::Null };
    serde_json::json!({
        "sequence": ev.sequence, "kind": kind.to_lowercase(), "state": state, "step": ev.step, "steps": ev.steps,
        "percent": finite(ev.percent), "eta_s": finite(ev.eta_s), "energy_drift": finite(ev.energy_drift),
        "sim_time_s": finite(ev.sim_time_s), "end_time_s": finite(ev.end_time_s), "message": ev.message,
        "final": super::convert::is_final(ev.state), "at_unix": ev.at_unix, "workers": workers,
    })
}

/// The page's script: follows the events, updates the page, reloads the plot at checkpoints
/// and state changes, and shows the results once the job has ended.
const SCRIPT: &str = r#"
(function(){
  const $=id=>document.getElementById(id);
  const root=$('job'); let received=0;
  function fmt(x,d){return (x===null||x===undefined)?'':Number(x).toPrecision(d||4);}
  function eta(s){if(s===null||s<0)return 'unknown';s=Math.round(s);return s>=60?Math.floor(s/60)+' min '+(s%60)+' s':s+' s';}
  const es=new EventSource('/jobs/'+root.dataset.id+'/events');
  es.addEventListener('job',e=>{
    const ev=JSON.parse(e.data); received++;
    root.dataset.seq=ev.sequence; root.dataset.received=received;
    if(ev.kind!=='not_retained'){
      $('state').textContent=ev.state; $('state').className='state '+ev.state; root.dataset.state=ev.state;
      $('bar').value=ev.percent||0; $('pct').textContent=fmt(ev.percent,3)+' %';
      $('step').textContent=ev.step+' / '+ev.steps; $('eta').textContent=eta(ev.eta_s);
      $('drift').textContent=fmt(ev.energy_drift,3); $('simtime').textContent=fmt(ev.sim_time_s,4)+' s of '+fmt(ev.end_time_s,4)+' s';
      if(ev.workers.length){$('workers').innerHTML=ev.workers.map(w=>'<tr><td>'+w.id+'</td><td>'+w.address+'</td><td>'+w.state+'</td><td>'+w.boxes+'</td><td>'+fmt(w.measured,3)+'</td><td>'+fmt(w.advertised,3)+'</td></tr>').join('');}
    }
    if(ev.message){const li=document.createElement('div');li.textContent='#'+ev.sequence+' '+ev.kind+' '+ev.state+': '+ev.message;$('log').prepend(li);}
    if(ev.kind==='checkpoint'||ev.kind==='state'){$('plot').src='/jobs/'+root.dataset.id+'/stress.svg?seq='+ev.sequence;}
    if(ev.final){
      root.dataset.liveFinal='1'; es.close();
      fetch('/jobs/'+root.dataset.id+'/results').then(r=>r.text()).then(h=>{$('results').innerHTML=h;root.dataset.results='1';});
      $('plot').src='/jobs/'+root.dataset.id+'/stress.svg?final';
    }
  });
  es.addEventListener('end',()=>es.close());
  es.addEventListener('failure',e=>{$('log').prepend(document.createTextNode('stream: '+JSON.parse(e.data).message));es.close();});
})();
"#;

/// `GET /jobs/ID`: the job now; live updates come from its events.
pub(crate) fn job_page(core: &Core, id: &str) -> Result<String, JobError> {
    let j = core.get(id)?;
    let p = percent(&j);
    let live = !j.state.is_final();
    // The stored events: the log (newest first) and the last drift, as the script shows them.
    let events: Vec<pb::JobEvent> = lock(&core.store).events_after(id, 0, 100_000)?.iter().map(super::convert::event_of).collect();
    let drift = events.iter().rev().find(|e| e.energy_drift != 0.0).map_or(String::new(), |e| format!("{:.3e}", e.energy_drift));
    let mut log = String::new();
    // A live page's script replays every event into the log itself.
    for e in events.iter().rev().filter(|e| !live && !e.message.is_empty()).take(200) {
        let ev = event_json(e);
        let _ = write!(
            log,
            "<div>#{} {} {}: {}</div>",
            e.sequence,
            ev["kind"].as_str().unwrap_or(""),
            ev["state"].as_str().unwrap_or(""),
            esc(&e.message)
        );
    }
    let body = format!(
        "<p><a href=\"/\">all jobs</a></p><h1>job {eid}</h1>\
         <div id=\"job\" data-id=\"{eid}\" data-state=\"{st}\" data-seq=\"0\" data-received=\"0\">\
         <dl><dt>scene</dt><dd>{scene}</dd><dt>state</dt><dd id=\"state\" class=\"state {st}\">{st}</dd>\
         <dt>progress</dt><dd><progress id=\"bar\" max=\"100\" value=\"{p:.1}\"></progress> <span id=\"pct\">{p:.1} %</span></dd>\
         <dt>step</dt><dd id=\"step\">{step} / {steps}</dd><dt>simulated time</dt><dd id=\"simtime\">{sim:.4e} s</dd>\
         <dt>ETA</dt><dd id=\"eta\">{eta}</dd><dt>energy drift |E-E0|/scale</dt><dd id=\"drift\">{drift}</dd>\
         <dt>state digest</dt><dd id=\"digest\">{digest}</dd><dt>note</dt><dd id=\"note\">{err}</dd></dl>\
         <h2>workers</h2><table><tr><th>worker</th><th>address</th><th>state</th><th>boxes</th><th>measured atom-steps/s</th>\
         <th>advertised atom-steps/s</th></tr><tbody id=\"workers\"><tr><td colspan=\"6\">MD in the orchestrator's process, or none yet</td></tr></tbody></table>\
         <h2>stress profile (newest snapshot)</h2><img id=\"plot\" alt=\"stress profile\" width=\"640\" height=\"320\" src=\"/jobs/{eid}/stress.svg\">\
         <h2>events</h2><div id=\"log\">{log}</div><h2>results</h2><div id=\"results\">{results}</div></div>{script}",
        eid = esc(&j.id),
        st = j.state.as_str(),
        scene = esc(&j.scene),
        step = j.step,
        steps = j.steps,
        sim = j.sim_time,
        eta = if live { "unknown" } else { "none (ended)" },
        digest = esc(&j.state_digest),
        err = esc(&j.error),
        results = if live { "(when the job has ended)".to_string() } else { results(core, id) },
        script = if live { format!("<script>{SCRIPT}</script>") } else { String::new() },
    );
    Ok(page(&format!("mscale job {}", j.id), &body))
}

/// `GET /jobs/ID/results`: links to every file of the run directory.
pub(crate) fn results(core: &Core, id: &str) -> String {
    let Ok(root) = core.run_root(id) else { return "<p>no run directory yet</p>".into() };
    let files = run_files(&root).unwrap_or_default();
    let mut out = format!(
        "<p id=\"nfiles\" data-n=\"{}\">{} files (or all at once: <code>mscale fetch {} --out DIR</code>)</p><ul>",
        files.len(),
        files.len(),
        esc(id)
    );
    for f in &files {
        let _ = write!(out, "<li><a href=\"/jobs/{}/files/{}\">{}</a></li>", esc(id), esc(f), esc(f));
    }
    out.push_str("</ul>");
    out
}

/// The newest snapshot of a run: (step, time, CSV text).
fn newest_snapshot(core: &Core, id: &str) -> Option<(u64, f64, String)> {
    let root = core.run_root(id).ok()?;
    let index = std::fs::read_to_string(root.join("snapshots/index.csv")).ok()?;
    let line = index.lines().rev().find(|l| l.split(',').next().is_some_and(|s| s.parse::<u64>().is_ok()))?;
    let mut f = line.splitn(3, ',');
    let (step, time, file) = (f.next()?.parse().ok()?, f.next()?.parse().ok()?, f.next()?.trim().to_string());
    let path = super::fetch::contained(&root, &format!("snapshots/{file}")).ok()?;
    Some((step, time, std::fs::read_to_string(path).ok()?))
}

/// `GET /jobs/ID/stress.svg`: sigma_xx (GPa) against x (nm) of the newest snapshot.
pub(crate) fn stress_svg(core: &Core, id: &str) -> Result<String, JobError> {
    core.get(id)?;
    let (w, h, (l, r, t, b)) = (640.0, 320.0, (70.0, 35.0, 30.0, 45.0));
    let mut svg = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\" font-family=\"sans-serif\" font-size=\"12\"><rect width=\"{w}\" height=\"{h}\" fill=\"white\"/>"
    );
    let points = newest_snapshot(core, id).and_then(|(step, time, csv)| {
        let mut lines = csv.lines();
        let head: Vec<&str> = lines.next()?.split(',').collect();
        let (xi, si) = (head.iter().position(|c| *c == "x")?, head.iter().position(|c| *c == "sxx")?);
        let mut pts: Vec<(f64, f64)> = lines
            .filter_map(|l| {
                let c: Vec<&str> = l.split(',').collect();
                Some((c.get(xi)?.parse::<f64>().ok()? * 1e9, c.get(si)?.parse::<f64>().ok()? / 1e9))
            })
            .filter(|(x, s)| x.is_finite() && s.is_finite())
            .collect();
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        (!pts.is_empty()).then_some((step, time, pts))
    });
    let Some((step, time, pts)) = points else {
        svg.push_str(&format!("<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">no snapshot yet</text></svg>", w / 2.0, h / 2.0));
        return Ok(svg);
    };
    let range = |v: &mut dyn Iterator<Item = f64>| {
        let (lo, hi) = v.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| (a.min(x), b.max(x)));
        if hi - lo > 1e-300 { (lo, hi) } else { (lo - 1.0, hi + 1.0) }
    };
    let (x0, x1) = range(&mut pts.iter().map(|p| p.0));
    let (y0, y1) = range(&mut pts.iter().map(|p| p.1));
    let px = |x: f64| l + (x - x0) / (x1 - x0) * (w - l - r);
    let py = |y: f64| h - b - (y - y0) / (y1 - y0) * (h - t - b);
    let path: Vec<String> = pts.iter().map(|&(x, y)| format!("{:.1},{:.1}", px(x), py(y))).collect();
    let _ = write!(
        svg,
        "<text x=\"{l}\" y=\"18\">sigma_xx at step {step} (t = {time:.4e} s), {} points</text>\
         <rect x=\"{l}\" y=\"{t}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"#999\"/>\
         <polyline id=\"profile\" data-points=\"{}\" fill=\"none\" stroke=\"#1456b8\" stroke-width=\"1.5\" points=\"{}\"/>",
        pts.len(),
        w - l - r,
        h - t - b,
        pts.len(),
        path.join(" ")
    );
    for (y, anchor) in [(y0, "end"), (y1, "end")] {
        let _ = write!(svg, "<text x=\"{}\" y=\"{:.1}\" text-anchor=\"{anchor}\">{y:.3}</text>", l - 4.0, py(y) + 4.0);
    }
    for x in [x0, x1] {
        let _ = write!(svg, "<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">{x:.3}</text>", px(x), h - b + 16.0);
    }
    let _ = write!(
        svg,
        "<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">x (nm)</text><text transform=\"translate(14,{:.1}) rotate(-90)\" text-anchor=\"middle\">sigma_xx (GPa)</text></svg>",
        l + (w - l - r) / 2.0,
        h - 6.0,
        t + (h - t - b) / 2.0
    );
    Ok(svg)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn html_is_escaped() {
        assert_eq!(esc("<a href=\"x\">&'"), "&lt;a href=&quot;x&quot;&gt;&amp;&#39;");
    }

    #[test]
    fn events_read_as_the_page_expects() {
        let ev = pb::JobEvent {
            state: pb::JobState::Completed as i32,
            kind: pb::JobEventKind::Checkpoint as i32,
            sequence: 7,
            eta_s: f64::NAN,
            ..Default::default()
        };
        let j = event_json(&ev);
        assert_eq!(
            (j["state"].as_str(), j["kind"].as_str(), j["final"].as_bool(), j["sequence"].as_u64()),
            (Some("completed"), Some("checkpoint"), Some(true), Some(7))
        );
        assert!(j["eta_s"].is_null(), "no NaN in the page's JSON");
    }
}
