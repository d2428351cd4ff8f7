//! Static checks of deploy/prometheus and deploy/grafana: the scrape configuration is valid
//! YAML that scrapes the orchestrator (HTTPS, bearer token from a file) and the workers at
//! `/metrics`; the Grafana dashboard is valid JSON whose every panel has PromQL targets on the
//! Prometheus data source, and every metric those expressions name is one the code registers
//! (as exposed: counters with `_total`, histograms with `_bucket`, `_sum`, `_count`). The live
//! check (the same names in real scrapes) is orchestrator/tests/http.rs.

// A panic is how these tests report a failure.
#![allow(clippy::unwrap_used)]

use std::collections::BTreeSet;
use std::path::PathBuf;

fn repo() -> PathBuf {
    mscale_testkit::repo()
}

/// The exposed names of the metrics registered in `file` (`r.register("NAME", ...)` calls,
/// the metric's type read from the field's declaration in the same file).
fn registered(file: &str) -> BTreeSet<String> {
    let text = std::fs::read_to_string(repo().join(file)).unwrap();
    let flat: String = text.split_whitespace().collect::<Vec<_>>().join(" ");
    let mut out = BTreeSet::new();
    for part in flat.split("r.register(").skip(1) {
        let name = part.split('"').nth(1).unwrap().to_string();
        // The field registered: `m.FIELD.clone()` at the end of the call.
        let field = part.split(".clone()").next().unwrap().rsplit("m.").next().unwrap().trim().to_string();
        let decl = text
            .lines()
            .map(str::trim)
            .find(|l| {
                l.starts_with(&format!("pub {field}:"))
                    || l.starts_with(&format!("pub(crate) {field}:"))
                    || l.starts_with(&format!("{field}:"))
            })
            .unwrap_or_else(|| panic!("{file}: no declaration of the field {field} of {name}"));
        let ty = decl.split_once(':').unwrap().1;
        if ty.contains("Histogram") {
            for s in ["_bucket", "_sum", "_count"] {
                out.insert(format!("{name}{s}"));
            }
        } else if ty.contains("Counter") {
            out.insert(format!("{name}_total"));
        } else {
            out.insert(name);
        }
    }
    assert!(out.len() > 10, "{file}: {out:?}");
    out
}

#[test]
fn the_prometheus_configuration_scrapes_the_orchestrator_and_the_workers() {
    let path = repo().join("deploy/prometheus/prometheus.yml");
    let doc: serde_yaml::Value = serde_yaml::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let jobs = doc["scrape_configs"].as_sequence().unwrap();
    let job = |name: &str| jobs.iter().find(|j| j["job_name"].as_str() == Some(name)).unwrap_or_else(|| panic!("no scrape job {name}"));
    let o = job("mscale-orchestrator");
    assert_eq!(o["scheme"].as_str(), Some("https"), "the orchestrator's HTTP port serves HTTPS when it has TLS (required off loopback)");
    assert_eq!(o["metrics_path"].as_str(), Some("/metrics"));
    assert_eq!(o["authorization"]["type"].as_str(), Some("Bearer"));
    assert!(o["authorization"]["credentials_file"].as_str().is_some_and(|f| f.starts_with('/')));
    assert!(o["tls_config"]["ca_file"].as_str().is_some());
    let w = job("mscale-md-workers");
    assert_eq!(w["metrics_path"].as_str(), Some("/metrics"));
    for j in [o, w] {
        let targets = j["static_configs"][0]["targets"].as_sequence().unwrap();
        assert!(!targets.is_empty());
        for t in targets {
            let t = t.as_str().unwrap();
            let port = t.rsplit_once(':').and_then(|(_, p)| p.parse::<u16>().ok());
            assert!(port.is_some_and(|p| p > 0), "target {t} is not HOST:PORT");
        }
    }
}

#[test]
fn the_grafana_dashboard_plots_only_metrics_the_code_exposes() {
    let mut known = registered("orchestrator/src/service/metrics.rs");
    known.extend(registered("md-worker/src/metrics.rs"));
    let dir = repo().join("deploy/grafana");
    let mut files = 0;
    for f in std::fs::read_dir(&dir).unwrap().flatten().filter(|f| f.path().extension().is_some_and(|e| e == "json")) {
        files += 1;
        let name = f.path().display().to_string();
        let dash: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(f.path()).unwrap()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(dash["title"].as_str().is_some() && dash["uid"].as_str().is_some(), "{name}: no title or uid");
        let panels = dash["panels"].as_array().unwrap();
        assert!(panels.len() >= 10, "{name}");
        let mut ids = BTreeSet::new();
        for p in panels {
            assert!(ids.insert(p["id"].as_u64().unwrap()), "{name}: panel id {} twice", p["id"]);
            assert_eq!(p["datasource"]["type"].as_str(), Some("prometheus"), "{name}: {}", p["title"]);
            for k in ["x", "y", "w", "h"] {
                assert!(p["gridPos"][k].as_u64().is_some(), "{name}: {} has no gridPos.{k}", p["title"]);
            }
            let targets = p["targets"].as_array().unwrap();
            assert!(!targets.is_empty(), "{name}: {} has no target", p["title"]);
            for t in targets {
                let expr = t["expr"].as_str().unwrap();
                assert_eq!(expr.matches('(').count(), expr.matches(')').count(), "{name}: unbalanced {expr}");
                let used: Vec<&str> = expr
                    .split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
                    .filter(|w| w.starts_with("mscale_") || w.starts_with("mdworker_"))
                    .collect();
                assert!(!used.is_empty(), "{name}: {expr} names no mscale metric");
                for m in used {
                    assert!(known.contains(m), "{name}: {expr} uses {m}, which the code does not expose (it exposes {known:?})");
                }
            }
        }
    }
    assert!(files >= 1, "no dashboard in deploy/grafana");
}
