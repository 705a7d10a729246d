//! `zenoh-probe`: what an intruder, or a witness, can do with one zenoh identity. The
//! multi-host test (`deploy/test/multihost.py`) uses it to forge puts and queries with a
//! device's certificate, to subscribe where that device must not see, and to count what
//! arrives. It prints one JSON line; it never decodes what it receives (it counts bytes
//! and a marker), so it is also a probe for any payload.

use std::time::Duration;

use clap::{Parser, Subcommand};
use serde_json::json;
use transport::ZenohArgs;

#[derive(Parser)]
struct Cli {
    #[command(flatten)]
    zenoh: ZenohArgs,
    /// Give up opening the session after this long (s): a refused identity must not hang.
    #[arg(long, default_value_t = 10.0)]
    open_timeout: f64,
    #[command(subcommand)]
    what: What,
}

#[derive(Subcommand)]
enum What {
    /// Open a session and close it: exit 0 if the router took us, 1 if not.
    Open,
    /// Put `count` payloads `MARKER-i` on `key`, one every `interval_ms`.
    Put {
        #[arg(long)]
        key: String,
        #[arg(long, default_value_t = 100)]
        count: u32,
        #[arg(long, default_value_t = 10)]
        interval_ms: u64,
        #[arg(long, default_value = "FORGED")]
        marker: String,
    },
    /// Subscribe to each `key` for `secs` and count samples, and those whose payload
    /// starts with `marker`, per key.
    Sub {
        #[arg(long, required = true)]
        key: Vec<String>,
        #[arg(long)]
        secs: f64,
        #[arg(long, default_value = "FORGED")]
        marker: String,
        /// Also write every payload received, one hex line each, to this file (a
        /// capture to play back with `replay`).
        #[arg(long)]
        save: Option<std::path::PathBuf>,
    },
    /// Put every payload of a `sub --save` file on `key` as it was captured, one every
    /// `interval_ms`, `rounds` times over.
    Replay {
        #[arg(long)]
        key: String,
        #[arg(long)]
        file: std::path::PathBuf,
        #[arg(long, default_value_t = 10)]
        interval_ms: u64,
        #[arg(long, default_value_t = 1)]
        rounds: u32,
    },
    /// Send `count` queries on `key` (with `payload_hex` as payload, if given) and count the
    /// replies: good ones, those whose payload starts with `marker`, and errors.
    Get {
        #[arg(long)]
        key: String,
        #[arg(long, default_value_t = 10)]
        count: u32,
        #[arg(long)]
        payload_hex: Option<String>,
        #[arg(long, default_value = "FORGED")]
        marker: String,
    },
    /// Delete `key` `count` times.
    Delete {
        #[arg(long)]
        key: String,
        #[arg(long, default_value_t = 10)]
        count: u32,
    },
    /// Serve `key` for `secs`, answering every query with `marker`; count the queries.
    Queryable {
        #[arg(long)]
        key: String,
        #[arg(long)]
        secs: f64,
        #[arg(long, default_value = "FORGED")]
        marker: String,
    },
    /// Hold a liveliness token on `key` for `secs`.
    Token {
        #[arg(long)]
        key: String,
        #[arg(long)]
        secs: f64,
    },
    /// List the liveliness tokens under `key`.
    Alive {
        #[arg(long)]
        key: String,
    },
}

fn hex(s: &str) -> anyhow::Result<Vec<u8>> {
    anyhow::ensure!(s.len() % 2 == 0, "odd hex length");
    (0..s.len())
        .step_by(2)
        .map(|i| Ok(u8::from_str_radix(&s[i..i + 2], 16)?))
        .collect()
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    match run(cli).await {
        Ok(v) => {
            println!("{v}");
            std::process::ExitCode::SUCCESS
        }
        Err(e) => {
            println!("{}", json!({ "error": format!("{e:#}") }));
            std::process::ExitCode::FAILURE
        }
    }
}

async fn run(cli: Cli) -> anyhow::Result<serde_json::Value> {
    let session = tokio::time::timeout(Duration::from_secs_f64(cli.open_timeout), cli.zenoh.open())
        .await
        .map_err(|_| anyhow::anyhow!("no session after {} s", cli.open_timeout))??;
    let s = &session;
    let out = match cli.what {
        What::Open => Ok(json!({ "opened": true })),
        What::Put {
            key,
            count,
            interval_ms,
            marker,
        } => put(s, &key, count, interval_ms, &marker).await,
        What::Sub {
            key,
            secs,
            marker,
            save,
        } => sub(s, key, secs, &marker, save.as_deref()).await,
        What::Replay {
            key,
            file,
            interval_ms,
            rounds,
        } => replay(s, &key, &file, interval_ms, rounds).await,
        What::Get {
            key,
            count,
            payload_hex,
            marker,
        } => get(s, &key, count, payload_hex.as_deref(), &marker).await,
        What::Delete { key, count } => delete(s, &key, count).await,
        What::Queryable { key, secs, marker } => queryable(s, &key, secs, marker).await,
        What::Token { key, secs } => token(s, &key, secs).await,
        What::Alive { key } => alive(s, &key).await,
    };
    let _ = session.close().await;
    out
}

type Session = zenoh::Session;

async fn put(
    session: &Session,
    key: &str,
    count: u32,
    interval_ms: u64,
    marker: &str,
) -> anyhow::Result<serde_json::Value> {
    let mut errors = 0;
    for i in 0..count {
        if session.put(key, format!("{marker}-{i}")).await.is_err() {
            errors += 1;
        }
        tokio::time::sleep(Duration::from_millis(interval_ms)).await;
    }
    Ok(json!({ "put": count, "errors": errors }))
}

/// Per key: received, marked, deletes.
type Counts = std::sync::Arc<std::sync::Mutex<std::collections::BTreeMap<String, (u64, u64, u64)>>>;

async fn sub(
    session: &Session,
    keys: Vec<String>,
    secs: f64,
    marker: &str,
    save: Option<&std::path::Path>,
) -> anyhow::Result<serde_json::Value> {
    let counts = Counts::default();
    let saved = std::sync::Arc::new(std::sync::Mutex::new(Vec::<String>::new()));
    let mut subs = Vec::new();
    for k in keys {
        counts.lock().unwrap().insert(k.clone(), (0, 0, 0));
        let (c, m, kk) = (counts.clone(), marker.to_string(), k.clone());
        let keep = save.map(|_| saved.clone());
        subs.push(
            session
                .declare_subscriber(&k)
                .callback(move |s| {
                    let bytes = s.payload().to_bytes();
                    if let Some(keep) = &keep {
                        let line = bytes.iter().map(|b| format!("{b:02x}")).collect();
                        keep.lock().unwrap().push(line);
                    }
                    let forged = bytes.starts_with(m.as_bytes());
                    let delete = s.kind() == zenoh::sample::SampleKind::Delete;
                    if let Some(e) = c.lock().unwrap().get_mut(&kk) {
                        e.0 += 1;
                        e.1 += forged as u64;
                        e.2 += delete as u64;
                    }
                })
                .await
                .map_err(|e| anyhow::anyhow!("subscriber {k}: {e}"))?,
        );
    }
    tokio::time::sleep(Duration::from_secs_f64(secs)).await;
    drop(subs);
    if let Some(path) = save {
        let lines = saved.lock().unwrap().join("\n");
        std::fs::write(path, lines + "\n")
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    }
    let counts = counts.lock().unwrap().clone();
    let per_key: serde_json::Map<String, serde_json::Value> = counts
        .iter()
        .map(|(k, (r, m, d))| {
            (
                k.clone(),
                json!({ "received": r, "marked": m, "deletes": d }),
            )
        })
        .collect();
    Ok(json!({
        "received": counts.values().map(|c| c.0).sum::<u64>(),
        "marked": counts.values().map(|c| c.1).sum::<u64>(),
        "per_key": per_key,
    }))
}

async fn replay(
    session: &Session,
    key: &str,
    file: &std::path::Path,
    interval_ms: u64,
    rounds: u32,
) -> anyhow::Result<serde_json::Value> {
    let text =
        std::fs::read_to_string(file).map_err(|e| anyhow::anyhow!("{}: {e}", file.display()))?;
    let payloads: Vec<Vec<u8>> = text
        .lines()
        .filter(|l| !l.is_empty())
        .map(hex)
        .collect::<anyhow::Result<_>>()?;
    let mut errors = 0;
    for _ in 0..rounds {
        for p in &payloads {
            if session.put(key, p.clone()).await.is_err() {
                errors += 1;
            }
            tokio::time::sleep(Duration::from_millis(interval_ms)).await;
        }
    }
    let put = payloads.len() as u64 * u64::from(rounds);
    Ok(json!({ "captured": payloads.len(), "put": put, "errors": errors }))
}

async fn get(
    session: &Session,
    key: &str,
    count: u32,
    payload_hex: Option<&str>,
    marker: &str,
) -> anyhow::Result<serde_json::Value> {
    let payload = payload_hex.map(hex).transpose()?;
    let (mut ok, mut err, mut marked) = (0u64, 0u64, 0u64);
    for _ in 0..count {
        let mut get = session.get(key).timeout(Duration::from_secs(1));
        if let Some(p) = &payload {
            get = get.payload(p.clone());
        }
        let replies = get.await.map_err(|e| anyhow::anyhow!("query {key}: {e}"))?;
        while let Ok(r) = replies.recv_async().await {
            match r.result() {
                Ok(s) => {
                    ok += 1;
                    marked += s.payload().to_bytes().starts_with(marker.as_bytes()) as u64;
                }
                Err(_) => err += 1,
            }
        }
    }
    Ok(json!({ "queries": count, "replies": ok, "marked_replies": marked, "error_replies": err }))
}

async fn delete(session: &Session, key: &str, count: u32) -> anyhow::Result<serde_json::Value> {
    let mut errors = 0;
    for _ in 0..count {
        if session.delete(key).await.is_err() {
            errors += 1;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    Ok(json!({ "deleted": count, "errors": errors }))
}

async fn queryable(
    session: &Session,
    key: &str,
    secs: f64,
    marker: String,
) -> anyhow::Result<serde_json::Value> {
    let n = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let seen = n.clone();
    let _q = session
        .declare_queryable(key)
        .callback(move |q| {
            seen.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let key = q.key_expr().clone();
            let marker = marker.clone();
            tokio::spawn(async move {
                let _ = q.reply(key, marker).await;
            });
        })
        .await
        .map_err(|e| anyhow::anyhow!("queryable {key}: {e}"))?;
    tokio::time::sleep(Duration::from_secs_f64(secs)).await;
    Ok(json!({ "queries_seen": n.load(std::sync::atomic::Ordering::Relaxed) }))
}

async fn token(session: &Session, key: &str, secs: f64) -> anyhow::Result<serde_json::Value> {
    let _t = session
        .liveliness()
        .declare_token(key)
        .await
        .map_err(|e| anyhow::anyhow!("token {key}: {e}"))?;
    tokio::time::sleep(Duration::from_secs_f64(secs)).await;
    Ok(json!({ "token": key }))
}

async fn alive(session: &Session, key: &str) -> anyhow::Result<serde_json::Value> {
    let replies = session
        .liveliness()
        .get(key)
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow::anyhow!("liveliness {key}: {e}"))?;
    let mut keys = Vec::new();
    while let Ok(r) = replies.recv_async().await {
        if let Ok(s) = r.result() {
            keys.push(s.key_expr().to_string());
        }
    }
    keys.sort();
    Ok(json!({ "alive": keys }))
}
