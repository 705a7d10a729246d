//! The command line:
//!
//! ```text
//! mfc-console --connect tcp/127.0.0.1:7447                       # then open http://127.0.0.1:8080/
//! mfc-console --zenoh-config operator.json5 --listen-http 127.0.0.1:9000 --config console.toml
//! ```
//!
//! It runs until SIGINT or SIGTERM. Without a `[login]` section in `--config`, the page is
//! served on loopback only, and anyone who can reach it acts as the console's operator
//! (the log says so when it starts); with one, people log in (a password, or a client
//! certificate over HTTPS) and the console acts for each by name. Off loopback, `[login]`
//! with `[login.https]` is required.
//!
//! ```text
//! mfc-console --hash-password < password.txt   # an argon2 hash for [[login.users]]
//! ```

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use clap::Parser;

use crate::http::{router, Guard};
use crate::login::HttpsSpec;
use crate::net::{wire, Console};
use crate::sessions::Doors;
use crate::settings::Settings;
use crate::ConsoleError;
use transport::https::TlsAcceptor;

/// The operator's live console: devices, live plots, status, gains and references, in a
/// browser.
#[derive(Debug, Parser)]
#[command(name = "mfc-console", version)]
pub struct ConsoleCli {
    #[command(flatten)]
    pub zenoh: transport::ZenohArgs,
    /// Address the page is served on (keep it on loopback unless a proxy authenticates).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub listen_http: SocketAddr,
    /// Settings (TOML; see `mfc_console::settings` for every field and its default).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// The operators' key file (`mfc-deploy` writes `keys/operator.key`): only replies
    /// sealed with it are shown. Without it, replies are taken unchecked (the log says so).
    #[arg(long)]
    pub key_file: Option<PathBuf>,
    /// The operator the console's requests name (`…/by/{operator}`): under a deployment,
    /// the common name of the certificate in its zenoh configuration. Default: the name
    /// that file gives (`mfc-deploy` writes it), else the local user, which services
    /// record as unverified.
    #[arg(long, env = "MFC_OPERATOR")]
    pub operator: Option<String>,
    /// Read a password from stdin (its first line), print its argon2id hash for a
    /// `[[login.users]]` entry's `password_hash`, and exit.
    #[arg(long, exclusive = true)]
    pub hash_password: bool,
}

/// The argon2id hash (PHC string, fresh random salt, the crate's default costs) of
/// `password`.
pub fn hash_password(password: &str) -> Result<String, String> {
    use argon2::password_hash::{rand_core::OsRng, PasswordHasher, SaltString};
    let salt = SaltString::generate(&mut OsRng);
    argon2::Argon2::default()
        .hash_password(password.as_bytes(), &salt)
        .map(|h| h.to_string())
        .map_err(|e| e.to_string())
}

/// Whether `password` is the one `phc` (an argon2 hash) was made from. Slow by design:
/// call it off the async threads.
pub fn verify_password(phc: &str, password: &str) -> bool {
    use argon2::password_hash::{PasswordHash, PasswordVerifier};
    PasswordHash::new(phc).is_ok_and(|h| {
        argon2::Argon2::default()
            .verify_password(password.as_bytes(), &h)
            .is_ok()
    })
}

fn print_hash() -> std::process::ExitCode {
    let mut line = String::new();
    if let Err(e) = std::io::stdin().read_line(&mut line) {
        eprintln!("mfc-console: reading the password from stdin: {e}");
        return std::process::ExitCode::FAILURE;
    }
    let password = line.trim_end_matches(['\n', '\r']);
    if password.is_empty() || password.len() > crate::login::MAX_PASSWORD {
        eprintln!(
            "mfc-console: give a password of 1 to {} bytes on stdin",
            crate::login::MAX_PASSWORD
        );
        return std::process::ExitCode::from(2);
    }
    match hash_password(password) {
        Ok(h) => {
            println!("{h}");
            std::process::ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("mfc-console: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Parse `args` and run until a signal; the process's exit code: 0 stopped by a signal, 1
/// failed (the reason on stderr), 2 bad usage.
pub fn main_with_args<I, T>(args: I) -> std::process::ExitCode
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    let cli = match ConsoleCli::try_parse_from(args) {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            return std::process::ExitCode::from(if e.use_stderr() { 2 } else { 0 });
        }
    };
    if cli.hash_password {
        return print_hash();
    }
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,zenoh=warn".into()),
        )
        .with_writer(std::io::stderr)
        .try_init();
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            eprintln!("mfc-console: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    // The signal handlers need the runtime: made inside it.
    match runtime.block_on(async { run(cli, transport::shutdown_signal()).await }) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("mfc-console: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// The page's HTTPS (`[login.https]`) and its acceptor, if any; refused off loopback
/// without it.
fn https_of(
    settings: &Settings,
    addr: SocketAddr,
) -> Result<(Option<HttpsSpec>, Option<TlsAcceptor>), ConsoleError> {
    let https = settings.login.as_ref().and_then(|l| l.https.clone());
    if !addr.ip().is_loopback() && https.is_none() {
        return Err(ConsoleError::Usage(format!(
            "listening on {addr}: off loopback the console needs [login] with [login.https] in \
             --config (without, anyone who reaches the port would act as its operator)"
        )));
    }
    if addr.ip().is_unspecified() && settings.allowed_hosts.is_empty() {
        tracing::warn!(
            "listening on {addr}: only localhost names are accepted as Host; name the others in allowed_hosts"
        );
    }
    let Some(h) = &https else {
        return Ok((None, None));
    };
    let files = transport::https::TlsFiles {
        cert_file: h.cert_file.clone(),
        key_file: h.key_file.clone(),
        client_ca_file: h.client_ca_file.clone(),
    };
    let a = transport::https::acceptor(&files, transport::https::ClientCerts::Optional)
        .map_err(|e| ConsoleError::Usage(format!("[login.https]: {e}")))?;
    Ok((https, Some(a)))
}

/// Run the console until `stop` completes.
pub async fn run(
    cli: ConsoleCli,
    stop: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ConsoleError> {
    let settings = match &cli.config {
        Some(p) => Settings::load(p)?,
        None => Settings::default(),
    };
    // Bind first: a port in use is reported before joining the network.
    let listener = tokio::net::TcpListener::bind(cli.listen_http)
        .await
        .map_err(|source| ConsoleError::Http {
            addr: cli.listen_http,
            source,
        })?;
    let addr = listener.local_addr().map_err(|source| ConsoleError::Http {
        addr: cli.listen_http,
        source,
    })?;
    let (https, acceptor) = https_of(&settings, addr)?;
    // No message larger than what the console reads is reassembled (see transport).
    let session = cli
        .zenoh
        .open_bounded(protocol::MAX_TRANSPORT_MESSAGE)
        .await
        .map_err(|e| ConsoleError::Zenoh(e.to_string()))?;
    let key = match &cli.key_file {
        Some(p) => Some(protocol::auth::Key::from_file(p)?),
        None => {
            tracing::warn!(
                "no --key-file: replies are shown without checking where they came from"
            );
            None
        }
    };
    let mut console = Console::new(session.clone(), settings.clone(), key);
    console.operator.name = match &cli.operator {
        Some(n) => Some(
            protocol::keys::check_id(n)
                .map_err(|e| ConsoleError::Usage(format!("--operator: {e}")))?
                .to_string(),
        ),
        None => transport::ops::default_name(&cli.zenoh),
    };
    tracing::info!(operator = ?console.operator.name, "the console's own requests (its polls) name this operator");
    let open_as = console
        .operator
        .name
        .clone()
        .unwrap_or_else(|| "console".into());
    let doors = Arc::new(Doors::new(
        settings.login.clone(),
        open_as.clone(),
        https.is_some(),
    ));
    match &settings.login {
        None => tracing::warn!(
            "no [login]: anyone who reaches {addr} acts as {open_as} (the demo's default, loopback only)"
        ),
        Some(l) => tracing::info!(
            users = l.users.len(),
            certificates = https.as_ref().is_some_and(|h| h.client_ca_file.is_some()),
            "people log in; the console acts for each by name"
        ),
    }
    let console = Arc::new(console);
    let wiring = wire(console.clone()).await?;
    let guard = Guard::new(addr, &settings.allowed_hosts, https.is_some());
    let scheme = if https.is_some() { "https" } else { "http" };
    tracing::info!(
        "console on {scheme}://{addr}/ (accepts Host: {})",
        guard.hosts().join(", ")
    );
    let app = router(console, guard, doors);
    let served = match acceptor {
        Some(a) => {
            transport::https::serve(listener, a, app, stop, "console").await;
            Ok(())
        }
        None => axum::serve(listener, app)
            .with_graceful_shutdown(stop)
            .await
            .map_err(|source| ConsoleError::Http { addr, source }),
    };
    drop(wiring);
    let _ = session.close().await;
    served
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_line_parses() {
        use clap::CommandFactory;
        ConsoleCli::command().debug_assert();
        let cli =
            ConsoleCli::try_parse_from(["mfc-console", "--connect", "tcp/127.0.0.1:7447"]).unwrap();
        assert_eq!(cli.listen_http.to_string(), "127.0.0.1:8080");
        assert_eq!(cli.zenoh.connect, ["tcp/127.0.0.1:7447"]);
    }
}
