//! Certificates: one CA, a server certificate for the router, a client certificate per
//! service, device and operator with CN = its name.
//!
//! Keys are ECDSA P-256 (what rustls and zenoh accept everywhere, and small). A certificate
//! already on disk is kept when it is still right (signed by this CA, same name and
//! addresses, not expiring soon), so generating again after adding a device touches no
//! other host.

use std::net::IpAddr;

use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa,
    Issuer, KeyPair, KeyUsagePurpose, PublicKeyData, SanType,
};
use time::{Duration, OffsetDateTime};
use x509_parser::prelude::{FromDer, GeneralName, X509Certificate};

use crate::DeployError;

fn pki_err(what: &str) -> impl FnOnce(rcgen::Error) -> DeployError + '_ {
    move |e| DeployError::Pki(format!("{what}: {e}"))
}

/// The fleet's certificate authority.
pub struct Ca {
    /// The CA certificate (PEM), given to every host.
    pub cert_pem: String,
    /// Its private key (PEM). Never leaves the machine that generates.
    pub key_pem: String,
    issuer: Issuer<'static, KeyPair>,
    der: Vec<u8>,
}

impl Ca {
    /// A new CA named `{name} {tag}`, valid `days` from now; `tag` is the tail of its public
    /// key in hex. Every fleet's CA has its own name: TLS finds a certificate's issuer by
    /// name, so two CAs of one name make a foreign certificate fail as `BadSignature` (a
    /// puzzle) instead of `UnknownIssuer` (the truth).
    pub fn create(name: &str, days: u32, now: OffsetDateTime) -> Result<Self, DeployError> {
        let key = KeyPair::generate().map_err(pki_err("CA key"))?;
        let spki = key.subject_public_key_info();
        let tag: String = spki[spki.len().saturating_sub(6)..]
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        let mut params = CertificateParams::default();
        let mut dn = DistinguishedName::new();
        dn.push(DnType::CommonName, format!("{name} {tag}"));
        params.distinguished_name = dn;
        params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
        params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        params.not_before = now - Duration::hours(1);
        params.not_after = now + Duration::days(days.into());
        let cert = params
            .self_signed(&key)
            .map_err(pki_err("CA certificate"))?;
        Self::load(&cert.pem(), &key.serialize_pem())
    }

    /// The CA kept on disk.
    pub fn load(cert_pem: &str, key_pem: &str) -> Result<Self, DeployError> {
        let key = KeyPair::from_pem(key_pem).map_err(pki_err("CA key"))?;
        let der = pem_der(cert_pem)?;
        let parsed = parse(&der)?;
        if !parsed.is_ca() {
            return Err(DeployError::Pki("the CA certificate is not a CA".into()));
        }
        if parsed.public_key().raw != key.subject_public_key_info().as_slice() {
            return Err(DeployError::Pki(
                "the CA key does not belong to the CA certificate".into(),
            ));
        }
        let issuer = Issuer::from_ca_cert_pem(cert_pem, key).map_err(pki_err("CA certificate"))?;
        Ok(Ca {
            cert_pem: cert_pem.to_string(),
            key_pem: key_pem.to_string(),
            issuer,
            der,
        })
    }

    /// When the CA certificate expires.
    pub fn not_after(&self) -> Result<OffsetDateTime, DeployError> {
        Ok(parse(&self.der)?.validity().not_after.to_datetime())
    }

    /// Issue a certificate for `name`: a server certificate with `hosts` as its
    /// subjectAltNames (the router), or a client certificate (everybody else).
    pub fn issue(
        &self,
        name: &str,
        usage: Usage<'_>,
        days: u32,
        now: OffsetDateTime,
    ) -> Result<Leaf, DeployError> {
        let key = KeyPair::generate().map_err(pki_err("key"))?;
        let mut params = CertificateParams::default();
        let mut dn = DistinguishedName::new();
        dn.push(DnType::CommonName, name);
        params.distinguished_name = dn;
        params.is_ca = IsCa::ExplicitNoCa;
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        params.use_authority_key_identifier_extension = true;
        params.not_before = now - Duration::hours(1);
        // Never past the CA: a chain is only as valid as its shortest link.
        params.not_after = (now + Duration::days(days.into())).min(self.not_after()?);
        match usage {
            Usage::Server(hosts) => {
                params.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth];
                params.subject_alt_names = hosts
                    .iter()
                    .map(|h| match h.parse::<IpAddr>() {
                        Ok(ip) => Ok(SanType::IpAddress(ip)),
                        Err(_) => h
                            .clone()
                            .try_into()
                            .map(SanType::DnsName)
                            .map_err(pki_err("router host name")),
                    })
                    .collect::<Result<_, _>>()?;
            }
            Usage::Client => {
                params.extended_key_usages = vec![ExtendedKeyUsagePurpose::ClientAuth];
            }
        }
        let cert = params
            .signed_by(&key, &self.issuer)
            .map_err(pki_err("certificate"))?;
        Ok(Leaf {
            cert_pem: cert.pem(),
            key_pem: key.serialize_pem(),
        })
    }

    /// Whether the certificate `cert_pem` (with its key `key_pem`) can be kept as the
    /// certificate of `name` for `usage`: `Ok(())`, or why it must be reissued.
    pub fn check(
        &self,
        cert_pem: &str,
        key_pem: &str,
        name: &str,
        usage: Usage<'_>,
        renew_before: Duration,
        now: OffsetDateTime,
    ) -> Result<(), String> {
        let der = pem_der(cert_pem).map_err(|e| e.to_string())?;
        let cert = parse(&der).map_err(|e| e.to_string())?;
        let ca = parse(&self.der).map_err(|e| e.to_string())?;
        cert.verify_signature(Some(ca.public_key()))
            .map_err(|_| "not signed by this CA".to_string())?;
        let key = KeyPair::from_pem(key_pem).map_err(|e| format!("key unreadable: {e}"))?;
        if cert.public_key().raw != key.subject_public_key_info().as_slice() {
            return Err("the key does not match the certificate".into());
        }
        let cn: Vec<_> = cert
            .subject()
            .iter_common_name()
            .filter_map(|a| a.as_str().ok())
            .collect();
        if cn != [name] {
            return Err(format!("common name {cn:?}, not {name:?}"));
        }
        let until = cert.validity().not_after.to_datetime();
        if until - renew_before <= now {
            return Err(format!("expires {}", until.date()));
        }
        if let Usage::Server(hosts) = usage {
            let mut have: Vec<String> = cert
                .subject_alternative_name()
                .ok()
                .flatten()
                .map(|s| {
                    s.value
                        .general_names
                        .iter()
                        .filter_map(|g| match g {
                            GeneralName::DNSName(d) => Some(d.to_string()),
                            GeneralName::IPAddress(b) => ip_of(b).map(|ip| ip.to_string()),
                            _ => None,
                        })
                        .collect()
                })
                .unwrap_or_default();
            let mut want: Vec<String> = hosts
                .iter()
                .map(|h| {
                    h.parse::<IpAddr>()
                        .map(|ip| ip.to_string())
                        .unwrap_or(h.clone())
                })
                .collect();
            have.sort();
            want.sort();
            if have != want {
                return Err(format!("names {have:?}, not {want:?}"));
            }
        }
        Ok(())
    }
}

/// What a certificate is for.
#[derive(Debug, Clone, Copy)]
pub enum Usage<'a> {
    /// TLS server (the router) for these names and addresses.
    Server(&'a [String]),
    /// TLS client (services, devices, operators).
    Client,
}

/// A certificate and its key.
pub struct Leaf {
    /// Certificate (PEM).
    pub cert_pem: String,
    /// Private key (PEM, PKCS#8).
    pub key_pem: String,
}

fn pem_der(pem: &str) -> Result<Vec<u8>, DeployError> {
    let (_, p) = x509_parser::pem::parse_x509_pem(pem.as_bytes())
        .map_err(|e| DeployError::Pki(format!("not a PEM certificate: {e}")))?;
    Ok(p.contents)
}

fn parse(der: &[u8]) -> Result<X509Certificate<'_>, DeployError> {
    X509Certificate::from_der(der)
        .map(|(_, c)| c)
        .map_err(|e| DeployError::Pki(format!("not an X.509 certificate: {e}")))
}

fn ip_of(b: &[u8]) -> Option<IpAddr> {
    match b.len() {
        4 => Some(IpAddr::from(<[u8; 4]>::try_from(b).ok()?)),
        16 => Some(IpAddr::from(<[u8; 16]>::try_from(b).ok()?)),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn now() -> OffsetDateTime {
        OffsetDateTime::from_unix_timestamp(1_800_000_000).unwrap()
    }

    #[test]
    fn issued_certificates_check_and_wrong_ones_do_not() {
        let ca = Ca::create("fleet CA", 3650, now()).unwrap();
        let hosts = vec!["10.0.0.1".to_string(), "router.example".to_string()];
        let r = ca
            .issue("router", Usage::Server(&hosts), 397, now())
            .unwrap();
        let d = ca.issue("aero-1", Usage::Client, 397, now()).unwrap();
        let renew = Duration::days(30);
        let ok = |l: &Leaf, n: &str, u| ca.check(&l.cert_pem, &l.key_pem, n, u, renew, now());
        assert_eq!(ok(&r, "router", Usage::Server(&hosts)), Ok(()));
        assert_eq!(ok(&d, "aero-1", Usage::Client), Ok(()));
        // Another name, other router addresses, another CA, a foreign key, near expiry.
        assert!(ok(&d, "aero-2", Usage::Client)
            .unwrap_err()
            .contains("common name"));
        let moved = vec!["10.0.0.2".to_string()];
        assert!(ok(&r, "router", Usage::Server(&moved))
            .unwrap_err()
            .contains("names"));
        let other = Ca::create("other", 3650, now()).unwrap();
        let e = other.check(
            &d.cert_pem,
            &d.key_pem,
            "aero-1",
            Usage::Client,
            renew,
            now(),
        );
        assert_eq!(e.unwrap_err(), "not signed by this CA");
        let e = ca.check(
            &d.cert_pem,
            &r.key_pem,
            "aero-1",
            Usage::Client,
            renew,
            now(),
        );
        assert!(e.unwrap_err().contains("key does not match"));
        let later = now() + Duration::days(380);
        let e = ca.check(
            &d.cert_pem,
            &d.key_pem,
            "aero-1",
            Usage::Client,
            renew,
            later,
        );
        assert!(e.unwrap_err().contains("expires"));
    }

    #[test]
    fn a_ca_reloads_and_refuses_a_foreign_key() {
        let ca = Ca::create("fleet CA", 3650, now()).unwrap();
        let again = Ca::load(&ca.cert_pem, &ca.key_pem).unwrap();
        let d = again.issue("aero-1", Usage::Client, 397, now()).unwrap();
        let renew = Duration::days(30);
        assert_eq!(
            ca.check(
                &d.cert_pem,
                &d.key_pem,
                "aero-1",
                Usage::Client,
                renew,
                now()
            ),
            Ok(())
        );
        let other = Ca::create("other", 3650, now()).unwrap();
        let e = Ca::load(&ca.cert_pem, &other.key_pem).err().unwrap();
        assert!(e.to_string().contains("does not belong"), "{e}");
    }

    #[test]
    fn leaves_never_outlive_the_ca() {
        let ca = Ca::create("fleet CA", 10, now()).unwrap();
        let d = ca.issue("aero-1", Usage::Client, 397, now()).unwrap();
        let der = pem_der(&d.cert_pem).unwrap();
        let until = parse(&der).unwrap().validity().not_after.to_datetime();
        assert!(until <= ca.not_after().unwrap());
    }
}
