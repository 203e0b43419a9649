//! The PostgreSQL store's link, from its URL: the driver's settings and the
//! TLS that `sslmode` asks for, as libpq reads it.
//!
//! - none or `disable`: plain TCP (a database on the same host or a private network);
//! - `require`: encrypted; the server's certificate is not checked (libpq's
//!   meaning), unless `sslrootcert` is given, which makes it `verify-ca`;
//! - `verify-ca`: the certificate's chain must lead to `sslrootcert` (a PEM file);
//! - `verify-full`: that, and the certificate must name the host connected to.
//!
//! `allow` and `prefer` fall back to plain text without saying so and are
//! refused. The TLS is rustls on the ring provider, as the server's own HTTPS.

use std::path::PathBuf;
use std::str::FromStr;
use std::sync::Arc;

use postgres::config::SslMode;
use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::client::WebPkiServerVerifier;
use rustls::crypto::WebPkiSupportedAlgorithms;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, ServerName, UnixTime};
use rustls::{CertificateError, ClientConfig, DigitallySignedStruct, RootCertStore, SignatureScheme};
use tokio_postgres_rustls::MakeRustlsConnect;

/// What `sslmode` asks of the link.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    Disable,
    Require,
    VerifyCa,
    VerifyFull,
}

pub struct Link {
    pub config: postgres::Config,
    pub tls: MakeRustlsConnect,
    pub mode: Mode,
}

/// The link `url` describes (a `postgres://` URL or libpq's `key=value` form);
/// errors name the setting.
pub fn link(url: &str) -> Result<Link, String> {
    let (rest, sslmode, sslrootcert) = take_tls_settings(url);
    let root = sslrootcert.map(PathBuf::from);
    let mode = match (sslmode.as_deref(), &root) {
        (None | Some("disable"), _) => Mode::Disable,
        (Some("require"), None) => Mode::Require,
        (Some("require" | "verify-ca"), Some(_)) => Mode::VerifyCa,
        (Some("verify-full"), Some(_)) => Mode::VerifyFull,
        (Some("verify-ca" | "verify-full"), None) => return Err("sslrootcert: verify-ca and verify-full need the CA certificate (a PEM file)".into()),
        (Some(m @ ("allow" | "prefer")), _) => {
            return Err(format!("sslmode={m} falls back to plain text silently; say disable, require, verify-ca or verify-full"));
        }
        (Some(m), _) => return Err(format!("sslmode: disable, require, verify-ca or verify-full, not {m:?}")),
    };
    let mut config = postgres::Config::from_str(&rest).map_err(|e| e.to_string())?;
    config.ssl_mode(if mode == Mode::Disable { SslMode::Disable } else { SslMode::Require });
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let verifier: Arc<dyn ServerCertVerifier> = match (mode, &root) {
        (Mode::VerifyCa | Mode::VerifyFull, Some(path)) => {
            let roots = roots(path)?;
            let webpki = WebPkiServerVerifier::builder_with_provider(Arc::new(roots), provider.clone()).build().map_err(|e| format!("sslrootcert: {e}"))?;
            if mode == Mode::VerifyFull { webpki } else { Arc::new(AnyName(webpki)) }
        }
        _ => Arc::new(Unchecked(provider.signature_verification_algorithms)),
    };
    let tls = ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| e.to_string())?
        .dangerous() // the verifier is chosen above, from sslmode
        .with_custom_certificate_verifier(verifier)
        .with_no_client_auth();
    Ok(Link { config, tls: MakeRustlsConnect::new(tls), mode })
}

/// `url` without `sslmode` and `sslrootcert` (which the driver does not
/// take in these forms), and their values.
fn take_tls_settings(url: &str) -> (String, Option<String>, Option<String>) {
    let (mut mode, mut root) = (None, None);
    let mut keep = |kv: &str, unescape: fn(&str) -> String| match kv.split_once('=') {
        Some(("sslmode", v)) => {
            mode = Some(unescape(v));
            false
        }
        Some(("sslrootcert", v)) => {
            root = Some(unescape(v));
            false
        }
        _ => true,
    };
    let rest = if url.contains("://") {
        match url.split_once('?') {
            Some((base, query)) => {
                let kept: Vec<&str> = query.split('&').filter(|kv| keep(kv, percent_decoded)).collect();
                if kept.is_empty() { base.to_string() } else { format!("{base}?{}", kept.join("&")) }
            }
            None => url.to_string(),
        }
    } else {
        url.split_whitespace().filter(|kv| keep(kv, |v| v.trim_matches('\'').to_string())).collect::<Vec<_>>().join(" ")
    };
    (rest, mode, root)
}

fn percent_decoded(s: &str) -> String {
    let bytes = s.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = (bytes[i] == b'%').then(|| s.get(i + 1..i + 3).and_then(|h| u8::from_str_radix(h, 16).ok())).flatten();
        match hex {
            Some(b) => {
                out.push(b);
                i += 3;
            }
            None => {
                out.push(bytes[i]);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

fn roots(path: &PathBuf) -> Result<RootCertStore, String> {
    let named = |e: &dyn std::fmt::Display| format!("sslrootcert {}: {e}", path.display());
    let mut roots = RootCertStore::empty();
    for cert in CertificateDer::pem_file_iter(path).map_err(|e| named(&e))? {
        roots.add(cert.map_err(|e| named(&e))?).map_err(|e| named(&e))?;
    }
    if roots.is_empty() {
        return Err(format!("sslrootcert {}: no certificate in it", path.display()));
    }
    Ok(roots)
}

/// `verify-ca`: the chain is checked, the name is not.
#[derive(Debug)]
struct AnyName(Arc<WebPkiServerVerifier>);

impl ServerCertVerifier for AnyName {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        intermediates: &[CertificateDer<'_>],
        server_name: &ServerName<'_>,
        ocsp: &[u8],
        now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        match self.0.verify_server_cert(end_entity, intermediates, server_name, ocsp, now) {
            Err(rustls::Error::InvalidCertificate(CertificateError::NotValidForName | CertificateError::NotValidForNameContext { .. })) => {
                Ok(ServerCertVerified::assertion())
            }
            other => other,
        }
    }
    fn verify_tls12_signature(&self, m: &[u8], c: &CertificateDer<'_>, d: &DigitallySignedStruct) -> Result<HandshakeSignatureValid, rustls::Error> {
        self.0.verify_tls12_signature(m, c, d)
    }
    fn verify_tls13_signature(&self, m: &[u8], c: &CertificateDer<'_>, d: &DigitallySignedStruct) -> Result<HandshakeSignatureValid, rustls::Error> {
        self.0.verify_tls13_signature(m, c, d)
    }
    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.0.supported_verify_schemes()
    }
}

/// `require`: encrypted, the certificate taken as it comes (the handshake's
/// signatures are still checked, so the key is the certificate's).
#[derive(Debug)]
struct Unchecked(WebPkiSupportedAlgorithms);

impl ServerCertVerifier for Unchecked {
    fn verify_server_cert(&self, _: &CertificateDer<'_>, _: &[CertificateDer<'_>], _: &ServerName<'_>, _: &[u8], _: UnixTime) -> Result<ServerCertVerified, rustls::Error> {
        Ok(ServerCertVerified::assertion())
    }
    fn verify_tls12_signature(&self, m: &[u8], c: &CertificateDer<'_>, d: &DigitallySignedStruct) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls12_signature(m, c, d, &self.0)
    }
    fn verify_tls13_signature(&self, m: &[u8], c: &CertificateDer<'_>, d: &DigitallySignedStruct) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls13_signature(m, c, d, &self.0)
    }
    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.0.supported_schemes()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tls_settings_come_out_of_either_form_and_bad_ones_are_named() {
        let (rest, mode, root) = take_tls_settings("postgres://u:p@db:5432/w?sslmode=verify-full&application_name=wp&sslrootcert=%2Fetc%2Fca.pem");
        assert_eq!((rest.as_str(), mode.as_deref(), root.as_deref()), ("postgres://u:p@db:5432/w?application_name=wp", Some("verify-full"), Some("/etc/ca.pem")));
        let (rest, mode, root) = take_tls_settings("host=db user=u sslmode=require dbname=w");
        assert_eq!((rest.as_str(), mode.as_deref(), root), ("host=db user=u dbname=w", Some("require"), None));
        assert_eq!(link("postgres://u@db/w").unwrap().mode, Mode::Disable);
        assert_eq!(link("postgres://u@db/w?sslmode=require").unwrap().mode, Mode::Require);
        for (url, says) in [
            ("postgres://u@db/w?sslmode=prefer", "plain text"),
            ("postgres://u@db/w?sslmode=verify-full", "sslrootcert"),
            ("postgres://u@db/w?sslmode=verify-ca&sslrootcert=/no/such.pem", "/no/such.pem"),
            ("postgres://u@db/w?sslmode=tight", "sslmode"),
        ] {
            let e = link(url).err().unwrap_or_else(|| panic!("{url} was taken"));
            assert!(e.contains(says), "{url}: {e}");
        }
    }
}
