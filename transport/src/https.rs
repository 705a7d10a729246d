//! HTTPS for the small HTTP sides of the processes (the metrics endpoint, the console):
//! rustls with its `ring` provider (the one zenoh's TLS links already build), and client
//! certificates of the deployment's CA, required (a scraper) or optional (a person, who may
//! log in with a password instead). The name a client certificate gives (its subject's
//! common name, which `mfc-deploy` sets to the operator's name) reaches each request as a
//! [`PeerName`] extension, so that a handler decides with the identity the handshake
//! verified and no header a client could write.

use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rustls::pki_types::{CertificateDer, PrivateKeyDer};
/// What [`acceptor`] makes and [`serve`] takes.
pub use tokio_rustls::TlsAcceptor;

/// Why TLS cannot be set up: the file and what is wrong with it.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct HttpsError(pub String);

/// The files of an HTTPS endpoint.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TlsFiles {
    /// The server's certificate chain (PEM).
    pub cert_file: PathBuf,
    /// Its private key (PEM).
    pub key_file: PathBuf,
    /// The CA whose client certificates are accepted (PEM); `None`: none asked for.
    pub client_ca_file: Option<PathBuf>,
}

/// Whether a client must present a certificate of `client_ca_file`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ClientCerts {
    /// No certificate, no connection (a scraper).
    Required,
    /// A certificate is verified when one is given; without one, the connection goes on and
    /// the request carries no [`PeerName`] (a person who logs in with a password).
    Optional,
}

/// The verified client certificate's common name, in every request of its connection;
/// `None` when the client gave no certificate (or one with no common name).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct PeerName(pub Option<String>);

fn pem_certs(path: &Path) -> Result<Vec<CertificateDer<'static>>, HttpsError> {
    let err = |e: &dyn std::fmt::Display| HttpsError(format!("{}: {e}", path.display()));
    let bytes = std::fs::read(path).map_err(|e| err(&e))?;
    let certs: Vec<_> = rustls_pemfile::certs(&mut &bytes[..])
        .collect::<Result<_, _>>()
        .map_err(|e| err(&e))?;
    if certs.is_empty() {
        return Err(err(&"no PEM certificate in it"));
    }
    Ok(certs)
}

fn pem_key(path: &Path) -> Result<PrivateKeyDer<'static>, HttpsError> {
    let err = |e: &dyn std::fmt::Display| HttpsError(format!("{}: {e}", path.display()));
    let bytes = std::fs::read(path).map_err(|e| err(&e))?;
    rustls_pemfile::private_key(&mut &bytes[..])
        .map_err(|e| err(&e))?
        .ok_or_else(|| err(&"no PEM private key in it"))
}

/// The acceptor for `files`, asking client certificates of its CA as `client` says
/// (`Required` with no CA file is refused: nothing could pass).
pub fn acceptor(files: &TlsFiles, client: ClientCerts) -> Result<TlsAcceptor, HttpsError> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ServerConfig::builder_with_provider(provider.clone())
        .with_safe_default_protocol_versions()
        .map_err(|e| HttpsError(e.to_string()))?;
    let builder = match (&files.client_ca_file, client) {
        (None, ClientCerts::Required) => {
            return Err(HttpsError(
                "client certificates are required, but no client_ca_file names their CA".into(),
            ))
        }
        (None, ClientCerts::Optional) => builder.with_no_client_auth(),
        (Some(ca), _) => {
            let mut roots = rustls::RootCertStore::empty();
            for c in pem_certs(ca)? {
                roots
                    .add(c)
                    .map_err(|e| HttpsError(format!("{}: {e}", ca.display())))?;
            }
            let verifier = rustls::server::WebPkiClientVerifier::builder_with_provider(
                Arc::new(roots),
                provider,
            );
            let verifier = match client {
                ClientCerts::Required => verifier,
                ClientCerts::Optional => verifier.allow_unauthenticated(),
            };
            let verifier = verifier
                .build()
                .map_err(|e| HttpsError(format!("client_ca_file: {e}")))?;
            builder.with_client_cert_verifier(verifier)
        }
    };
    let config = builder
        .with_single_cert(pem_certs(&files.cert_file)?, pem_key(&files.key_file)?)
        .map_err(|e| HttpsError(format!("cert_file and key_file: {e}")))?;
    Ok(TlsAcceptor::from(Arc::new(config)))
}

/// The subject's common name of a (verified) certificate.
pub fn common_name(der: &[u8]) -> Option<String> {
    let (_, cert) = x509_parser::parse_x509_certificate(der).ok()?;
    let cn = cert.subject().iter_common_name().next()?;
    cn.as_str().ok().map(str::to_string)
}

/// Serve `app` on `listener` through `acceptor` until `shutdown`: one task per
/// connection, each request with the connection's [`PeerName`]; a failed handshake is
/// logged at debug level (a scanner's noise) and closes that connection only. `what`
/// names the endpoint in the log.
pub async fn serve(
    listener: tokio::net::TcpListener,
    acceptor: TlsAcceptor,
    app: axum::Router,
    shutdown: impl Future<Output = ()> + Send + 'static,
    what: &'static str,
) {
    tokio::pin!(shutdown);
    loop {
        let (tcp, peer) = tokio::select! {
            r = listener.accept() => match r {
                Ok(x) => x,
                Err(e) => {
                    tracing::warn!("{what}: accept: {e}");
                    tokio::time::sleep(std::time::Duration::from_millis(100)).await;
                    continue;
                }
            },
            () = &mut shutdown => return,
        };
        let (acceptor, app) = (acceptor.clone(), app.clone());
        tokio::spawn(async move {
            let handshake =
                tokio::time::timeout(std::time::Duration::from_secs(10), acceptor.accept(tcp));
            let tls = match handshake.await {
                Ok(Ok(s)) => s,
                Ok(Err(e)) => return tracing::debug!(%peer, "{what}: TLS handshake refused: {e}"),
                Err(_) => return tracing::debug!(%peer, "{what}: TLS handshake timed out"),
            };
            let name = tls
                .get_ref()
                .1
                .peer_certificates()
                .and_then(|c| c.first())
                .and_then(|c| common_name(c));
            let app = app.layer(axum::Extension(PeerName(name)));
            let service = hyper_util::service::TowerToHyperService::new(app);
            let io = hyper_util::rt::TokioIo::new(tls);
            if let Err(e) = hyper::server::conn::http1::Builder::new()
                .serve_connection(io, service)
                .await
            {
                tracing::debug!(%peer, "{what}: connection: {e}");
            }
        });
    }
}
