//! Mutual TLS of `mscale serve --tls-client-ca`: clients and `md-worker serve --orchestrator`
//! workers must present a certificate signed by that authority; without one, or with one of
//! another authority, the orchestrator is not reached (the worker never registers).

// A panic is how these tests report a failure, also in their helper functions.
#![allow(clippy::unwrap_used)]

use mscale_testkit::{Listening, Proc, text};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::Duration;

const SMALL: &str = "../tests/data/small.toml";
const TOKEN: &str = "test-token-0123456789";

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_mscale")
}

/// A client certificate (`client.pem`, `client.key`) signed by the authority that
/// `mscale_testkit::tls_certificates` made in `dir`.
fn client_certificate(dir: &Path) -> (PathBuf, PathBuf) {
    let run = |args: &[&str]| {
        let o = Command::new("openssl").args(args).current_dir(dir).output().expect("openssl is needed for the TLS tests");
        assert!(o.status.success(), "openssl {args:?}: {}", text(&o));
    };
    run(&["req", "-newkey", "rsa:2048", "-nodes", "-keyout", "client.key", "-out", "client.csr", "-subj", "/CN=mscale worker"]);
    std::fs::write(dir.join("client.ext"), "basicConstraints=CA:FALSE\nextendedKeyUsage=clientAuth\n").unwrap();
    run(&[
        "x509",
        "-req",
        "-in",
        "client.csr",
        "-CA",
        "ca.pem",
        "-CAkey",
        "ca.key",
        "-CAcreateserial",
        "-out",
        "client.pem",
        "-days",
        "2",
        "-extfile",
        "client.ext",
    ]);
    (dir.join("client.pem"), dir.join("client.key"))
}

#[test]
fn with_tls_client_ca_only_certified_clients_and_workers_get_in() {
    let (tmp, token) = mscale_testkit::token_dir(TOKEN);
    let (ca, cert, key) = mscale_testkit::tls_certificates(tmp.path());
    let (client_cert, client_key) = client_certificate(tmp.path());
    let other = tmp.path().join("other");
    std::fs::create_dir_all(&other).unwrap();
    mscale_testkit::tls_certificates(&other);
    let (other_cert, other_key) = client_certificate(&other);

    let mut cmd = Command::new(bin());
    cmd.args(["serve", "--state", tmp.path().join("state").to_str().unwrap(), "--listen", "127.0.0.1:0"])
        .args(["--token-file", token.to_str().unwrap(), "--tls-cert", cert.to_str().unwrap(), "--tls-key", key.to_str().unwrap()])
        .args(["--tls-client-ca", ca.to_str().unwrap()])
        .env("RUST_LOG", "info");
    let Listening { proc, addr } = Listening::start(&mut cmd, "mscale serve: listening on ", Some(&tmp.path().join("serve.log")));
    let cli = |args: &[&str], identity: Option<(&Path, &Path)>| -> Output {
        let mut c = Command::new(bin());
        c.args(args).args(["--server", &format!("https://localhost:{}", addr.rsplit(':').next().unwrap())]);
        c.args(["--ca-file", ca.to_str().unwrap(), "--token-file", token.to_str().unwrap()]);
        if let Some((cert, key)) = identity {
            c.args(["--client-cert", cert.to_str().unwrap(), "--client-key", key.to_str().unwrap()]);
        }
        c.env_remove("MSCALE_TOKEN").env("RUST_LOG", "warn").output().unwrap()
    };
    let mine = Some((client_cert.as_path(), client_key.as_path()));
    let h = cli(&["health"], mine);
    assert!(h.status.success() && String::from_utf8_lossy(&h.stdout).contains("SERVING"), "{}\n{}", text(&h), proc.log());
    let s = cli(&["submit", SMALL], mine);
    assert!(s.status.success(), "{}", text(&s));
    // Without a client certificate, or with one of another authority: not reached.
    for (what, identity) in [("none", None), ("another authority's", Some((other_cert.as_path(), other_key.as_path())))] {
        let o = cli(&["status"], identity);
        assert!(!o.status.success(), "a client with {what} certificate got in: {}", text(&o));
    }

    // Workers: the certified one registers, the other does not.
    let worker = |name: &str, identity: Option<(&Path, &Path)>| -> Proc {
        let mut c = Command::new(mscale_testkit::prebuilt("md-worker", "md-worker"));
        c.args(["serve", "--listen", "127.0.0.1:0", "--device", "cpu", "--threads", "1", "--heartbeat-every", "1"])
            .args(["--orchestrator", &format!("https://localhost:{}", addr.rsplit(':').next().unwrap())])
            .args(["--token-file", token.to_str().unwrap(), "--ca-file", ca.to_str().unwrap(), "--throughput", "1e5"]);
        if let Some((cert, key)) = identity {
            c.args(["--client-cert", cert.to_str().unwrap(), "--client-key", key.to_str().unwrap()]);
        }
        c.env("RUST_LOG", "info").stdout(Stdio::null());
        Proc::spawn_logged(&mut c, &tmp.path().join(format!("{name}.log")))
    };
    let _good = worker("good", mine);
    let _bare = worker("bare", None);
    let workers = || {
        let o = cli(&["workers"], mine);
        assert!(o.status.success(), "{}", text(&o));
        String::from_utf8_lossy(&o.stdout).lines().filter(|l| l.contains(" live ")).count()
    };
    mscale_testkit::wait_until("the certified worker registers", Duration::from_secs(60), || workers() == 1);
    std::thread::sleep(Duration::from_secs(3));
    assert_eq!(workers(), 1, "a worker without a client certificate registered\n{}", proc.log());
    let bare_log = std::fs::read_to_string(tmp.path().join("bare.log")).unwrap_or_default();
    assert!(!bare_log.contains("joined the pool"), "{bare_log}");
}
