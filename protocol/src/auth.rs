//! Proof of origin for the loop's messages: who may speak for a device.
//!
//! Access control decides who may *put* on a key, but zenoh gives the receiver no proof of
//! who did: `SourceInfo` is the sender's own claim, a router that terminates TLS could
//! forge, and any holder of a service certificate may put on every device's keys. So the
//! messages prove themselves: each Sample, Command, SampleBatch and CommandBatch ends with
//! an HMAC-SHA256 (field 100, `mac`) under a key only the device and its controllers hold.
//!
//! Keys: a fleet's members share one [`Secret`] (from `mfc-deploy`, or made at start by a
//! demo); each device's [`Key`] is derived from it and the device id, so a plant holds its
//! own key only and a stolen plant speaks for itself alone. Gateways have one key each
//! (one proof per batch); operators' replies have a key of their own
//! ([`Secret::operator`]), so an operator that can check a reply cannot forge a command.
//!
//! The MAC covers a label naming the message's kind and every byte before the field, as
//! sent: the receiver checks the bytes it got, before decoding them, and a newer peer's
//! unknown fields are covered too. Replays are the protocol's business: a command names
//! the run and lease epoch it is for and a sample its run and `seq`, all under the MAC.

use ring::hmac;
use ring::rand::{SecureRandom, SystemRandom};

/// Bytes of a MAC (HMAC-SHA256).
pub const MAC_LEN: usize = 32;

/// The field's key (number 100, length-delimited) and length, as protobuf writes them.
const TRAILER_HEAD: [u8; 3] = [0xA2, 0x06, MAC_LEN as u8];

/// Bytes a sealed message has beyond its body.
pub const TRAILER_LEN: usize = TRAILER_HEAD.len() + MAC_LEN;

/// What a MAC vouches for: the kind of message, so that one kind never passes as another.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// A plant's sample (`mfc/v1/device/{id}/sample`).
    Sample,
    /// A controller's command (`mfc/v1/device/{id}/command`).
    Command,
    /// A gateway's batch of samples.
    SampleBatch,
    /// A controller's batch of commands for a gateway.
    CommandBatch,
    /// A reply to an operator's query (status, config, envelope, reference).
    Reply,
    /// An error reply to an operator's query ("does not serve", a bad key): as proven as
    /// a good one, so that a forger cannot show an operator a refusal either.
    ErrorReply,
    /// A fleet member's handover message: a shard's state, or a change it holds.
    Handover,
}

impl Kind {
    fn label(self) -> &'static [u8] {
        match self {
            Kind::Sample => b"mfc/v1/sample\0",
            Kind::Command => b"mfc/v1/command\0",
            Kind::SampleBatch => b"mfc/v1/sample-batch\0",
            Kind::CommandBatch => b"mfc/v1/command-batch\0",
            Kind::Reply => b"mfc/v1/reply\0",
            Kind::ErrorReply => b"mfc/v1/error-reply\0",
            Kind::Handover => b"mfc/v1/handover\0",
        }
    }
}

/// Why a sealed message was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum AuthError {
    /// The message does not end with a `mac` field of the right length.
    #[error("no proof of origin (the message does not end with its mac)")]
    Unsealed,
    /// The MAC does not match: another key, another kind, or altered bytes.
    #[error("the proof of origin does not match (forged, altered, or under another key)")]
    Mismatch,
}

/// Why a secret or key could not be read.
#[derive(Debug, thiserror::Error)]
pub enum KeyError {
    /// Not 64 hexadecimal digits.
    #[error("a key is 64 hexadecimal digits (32 bytes); got {0} characters")]
    Format(usize),
    /// The file could not be read.
    #[error("cannot read key file {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    /// The system's random source failed.
    #[error("the system's random source failed")]
    Random,
}

/// A fleet's shared secret: every device's, gateway's and the operators' keys derive from
/// it. Only the fleet's members hold it.
#[derive(Clone)]
pub struct Secret([u8; 32]);

impl std::fmt::Debug for Secret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Secret(..)")
    }
}

impl Secret {
    /// A new random secret (a demo's, made at start; `mfc-deploy`'s).
    pub fn random() -> Result<Self, KeyError> {
        let mut b = [0u8; 32];
        SystemRandom::new()
            .fill(&mut b)
            .map_err(|_| KeyError::Random)?;
        Ok(Self(b))
    }

    /// From its 64 hexadecimal digits (surrounding white space ignored).
    pub fn from_hex(text: &str) -> Result<Self, KeyError> {
        parse_hex(text).map(Self)
    }

    /// From a file holding the 64 digits.
    pub fn from_file(path: &std::path::Path) -> Result<Self, KeyError> {
        read_hex(path).map(Self)
    }

    /// The 64 hexadecimal digits, for a key file.
    pub fn to_hex(&self) -> String {
        to_hex(&self.0)
    }

    /// The key device `id` and its controllers share.
    pub fn device(&self, id: &str) -> Key {
        self.derive(b"mfc/v1/device-key\0", id)
    }

    /// The key gateway `id` and its controllers share (batches).
    pub fn gateway(&self, id: &str) -> Key {
        self.derive(b"mfc/v1/gateway-key\0", id)
    }

    /// The key under which members sign replies to operators' queries and operators check
    /// them.
    pub fn operator(&self) -> Key {
        self.derive(b"mfc/v1/operator-key\0", "")
    }

    /// The key fleet members seal their handover messages with (shard states, changes
    /// to hold). Only services hold the secret it derives from: an operator's or a
    /// device's key cannot forge a state a member would restore.
    pub fn member(&self) -> Key {
        self.derive(b"mfc/v1/member-key\0", "")
    }

    fn derive(&self, label: &[u8], id: &str) -> Key {
        let k = hmac::Key::new(hmac::HMAC_SHA256, &self.0);
        let mut ctx = hmac::Context::with_key(&k);
        ctx.update(label);
        ctx.update(id.as_bytes());
        let tag = ctx.sign();
        let mut bytes = [0u8; 32];
        bytes.copy_from_slice(tag.as_ref());
        Key::from_bytes(bytes)
    }
}

/// A key that seals and opens messages: a device's, a gateway's or the operators'.
#[derive(Clone)]
pub struct Key {
    bytes: [u8; 32],
    key: hmac::Key,
}

impl std::fmt::Debug for Key {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Key(..)")
    }
}

impl Key {
    /// From its 32 bytes.
    pub fn from_bytes(bytes: [u8; 32]) -> Self {
        Self {
            bytes,
            key: hmac::Key::new(hmac::HMAC_SHA256, &bytes),
        }
    }

    /// From its 64 hexadecimal digits.
    pub fn from_hex(text: &str) -> Result<Self, KeyError> {
        parse_hex(text).map(Self::from_bytes)
    }

    /// From a file holding the 64 digits (what `mfc-deploy` writes for a plant).
    pub fn from_file(path: &std::path::Path) -> Result<Self, KeyError> {
        read_hex(path).map(Self::from_bytes)
    }

    /// The 64 hexadecimal digits, for a key file.
    pub fn to_hex(&self) -> String {
        to_hex(&self.bytes)
    }

    /// The MAC of `body` as a message of `kind` sent in `context` (each part of it
    /// length-prefixed, so that no two contexts read alike).
    fn mac(&self, kind: Kind, context: &[&[u8]], body: &[u8]) -> hmac::Tag {
        let mut ctx = hmac::Context::with_key(&self.key);
        ctx.update(kind.label());
        for part in context {
            ctx.update(&(part.len() as u64).to_le_bytes());
            ctx.update(part);
        }
        ctx.update(body);
        ctx.sign()
    }

    /// Append the `mac` field to an encoded message of `kind` (whose own `mac` is empty).
    pub fn seal(&self, kind: Kind, body: Vec<u8>) -> Vec<u8> {
        self.seal_in(kind, &[], body)
    }

    /// [`Key::seal`] bound to a context the receiver knows too: a reply to an operator is
    /// bound to its key expression and to the request it answers, so that it cannot be
    /// passed off as another device's or as the answer to another change.
    pub fn seal_in(&self, kind: Kind, context: &[&[u8]], mut body: Vec<u8>) -> Vec<u8> {
        let tag = self.mac(kind, context, &body);
        body.reserve(TRAILER_LEN);
        body.extend_from_slice(&TRAILER_HEAD);
        body.extend_from_slice(tag.as_ref());
        body
    }

    /// The body of a sealed message of `kind`, if its MAC is this key's (compared in
    /// constant time). The body decodes as the message without its `mac`.
    pub fn open<'a>(&self, kind: Kind, sealed: &'a [u8]) -> Result<&'a [u8], AuthError> {
        self.open_in(kind, &[], sealed)
    }

    /// [`Key::open`] of a message sealed with [`Key::seal_in`] in `context`.
    pub fn open_in<'a>(
        &self,
        kind: Kind,
        context: &[&[u8]],
        sealed: &'a [u8],
    ) -> Result<&'a [u8], AuthError> {
        let (body, mac) = split(sealed)?;
        let tag = self.mac(kind, context, body);
        // Every byte compared whatever the first difference: no timing tells how much of
        // a forged MAC was right.
        let diff = tag
            .as_ref()
            .iter()
            .zip(mac)
            .fold(0u8, |acc, (a, b)| acc | (a ^ b));
        if std::hint::black_box(diff) == 0 {
            Ok(body)
        } else {
            Err(AuthError::Mismatch)
        }
    }
}

/// The context a reply to an operator is sealed in: the key expression it is sent on and
/// the payload of the query it answers (empty for a read).
pub fn reply_context<'a>(key_expr: &'a str, request: &'a [u8]) -> [&'a [u8]; 2] {
    [key_expr.as_bytes(), request]
}

/// A sealed message's body and MAC, if it ends with a well-formed `mac` field.
/// The body of a message that may be sealed, unchecked: what a client without the key
/// shows of a keyed service's error reply (its text without the MAC's bytes). Proves
/// nothing.
pub fn unchecked_body(bytes: &[u8]) -> &[u8] {
    split(bytes).map_or(bytes, |(body, _)| body)
}

fn split(sealed: &[u8]) -> Result<(&[u8], &[u8]), AuthError> {
    let Some(at) = sealed.len().checked_sub(TRAILER_LEN) else {
        return Err(AuthError::Unsealed);
    };
    let (body, trailer) = sealed.split_at(at);
    if trailer[..TRAILER_HEAD.len()] != TRAILER_HEAD {
        return Err(AuthError::Unsealed);
    }
    Ok((body, &trailer[TRAILER_HEAD.len()..]))
}

fn parse_hex(text: &str) -> Result<[u8; 32], KeyError> {
    let t = text.trim();
    let digits = t.as_bytes();
    if digits.len() != 64 {
        return Err(KeyError::Format(t.chars().count()));
    }
    let mut out = [0u8; 32];
    for (i, pair) in digits.chunks(2).enumerate() {
        let hi = (pair[0] as char).to_digit(16);
        let lo = (pair[1] as char).to_digit(16);
        match (hi, lo) {
            (Some(h), Some(l)) => out[i] = (h * 16 + l) as u8,
            _ => return Err(KeyError::Format(t.chars().count())),
        }
    }
    Ok(out)
}

fn read_hex(path: &std::path::Path) -> Result<[u8; 32], KeyError> {
    let text = std::fs::read_to_string(path).map_err(|source| KeyError::Read {
        path: path.display().to_string(),
        source,
    })?;
    parse_hex(&text)
}

fn to_hex(b: &[u8; 32]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{decode, encode, pb, PROTOCOL_VERSION};
    use proptest::prelude::*;

    fn secret() -> Secret {
        Secret::from_hex(&"0123456789abcdef".repeat(4)).unwrap()
    }

    fn sample() -> pb::Sample {
        pb::Sample {
            version: PROTOCOL_VERSION,
            device_id: "aero-1".into(),
            seq: 42,
            run_id: 7,
            outputs: vec![0.5, -0.25],
            ..Default::default()
        }
    }

    #[test]
    fn a_sealed_message_opens_under_its_key_and_decodes_with_its_mac() {
        let key = secret().device("aero-1");
        let sealed = key.seal(Kind::Sample, encode(&sample()));
        let body = key.open(Kind::Sample, &sealed).unwrap();
        assert_eq!(decode::<pb::Sample>(body).unwrap(), sample());
        // The whole sealed message decodes too, its MAC in `mac`.
        let whole = decode::<pb::Sample>(&sealed).unwrap();
        assert_eq!(whole.mac.len(), MAC_LEN);
        assert_eq!(whole.mac, sealed[sealed.len() - MAC_LEN..]);
    }

    #[test]
    fn another_device_kind_or_secret_does_not_open_it() {
        let s = secret();
        let sealed = s.device("aero-1").seal(Kind::Sample, encode(&sample()));
        assert_eq!(
            s.device("aero-2").open(Kind::Sample, &sealed),
            Err(AuthError::Mismatch)
        );
        assert_eq!(
            s.device("aero-1").open(Kind::Command, &sealed),
            Err(AuthError::Mismatch)
        );
        assert_eq!(
            s.gateway("aero-1").open(Kind::Sample, &sealed),
            Err(AuthError::Mismatch)
        );
        let other = Secret::random().unwrap();
        assert_eq!(
            other.device("aero-1").open(Kind::Sample, &sealed),
            Err(AuthError::Mismatch)
        );
    }

    #[test]
    fn an_unsealed_or_cut_message_is_unsealed() {
        let key = secret().device("aero-1");
        let plain = encode(&sample());
        assert_eq!(key.open(Kind::Sample, &plain), Err(AuthError::Unsealed));
        assert_eq!(key.open(Kind::Sample, &[]), Err(AuthError::Unsealed));
        let sealed = key.seal(Kind::Sample, plain);
        assert!(key.open(Kind::Sample, &sealed[..sealed.len() - 1]).is_err());
    }

    #[test]
    fn a_reply_opens_only_in_its_own_context() {
        let key = secret().operator();
        let sealed = key.seal_in(Kind::Reply, &[b"mfc/v1/a/status", b""], vec![8, 1]);
        assert!(key
            .open_in(Kind::Reply, &[b"mfc/v1/a/status", b""], &sealed)
            .is_ok());
        assert!(key
            .open_in(Kind::Reply, &[b"mfc/v1/b/status", b""], &sealed)
            .is_err());
        // Moving a byte from one part to the next is another context.
        assert!(key
            .open_in(Kind::Reply, &[b"mfc/v1/a/statu", b"s"], &sealed)
            .is_err());
        assert!(key.open(Kind::Reply, &sealed).is_err());
        // An error reply is not a good reply, nor the other way round.
        let err = key.seal_in(Kind::ErrorReply, &[b"mfc/v1/a/status", b""], b"no".to_vec());
        assert!(key
            .open_in(Kind::Reply, &[b"mfc/v1/a/status", b""], &err)
            .is_err());
        assert!(key
            .open_in(Kind::ErrorReply, &[b"mfc/v1/a/status", b""], &sealed)
            .is_err());
    }

    #[test]
    fn keys_read_back_from_their_hex_and_refuse_bad_text() {
        let s = Secret::random().unwrap();
        assert_eq!(Secret::from_hex(&s.to_hex()).unwrap().0, s.0);
        let k = s.device("x");
        assert_eq!(Key::from_hex(&k.to_hex()).unwrap().bytes, k.bytes);
        assert!(matches!(Key::from_hex("abc"), Err(KeyError::Format(3))));
        assert!(matches!(
            Key::from_hex(&"zz".repeat(32)),
            Err(KeyError::Format(64))
        ));
        assert_eq!(format!("{s:?} {k:?}"), "Secret(..) Key(..)");
    }

    #[test]
    fn derived_keys_differ_per_device_gateway_and_role() {
        let s = secret();
        let all = [
            s.device("a").bytes,
            s.device("b").bytes,
            s.gateway("a").bytes,
            s.operator().bytes,
        ];
        for (i, a) in all.iter().enumerate() {
            for b in &all[i + 1..] {
                assert_ne!(a, b);
            }
        }
        assert_eq!(s.device("a").bytes, secret().device("a").bytes);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(500))]
        /// Any change to any byte of a sealed message is refused.
        #[test]
        fn any_altered_byte_is_refused(at in 0usize..400, flip in 1u8..=255) {
            let key = secret().device("aero-1");
            let sealed = key.seal(Kind::Sample, encode(&sample()));
            let mut bad = sealed.clone();
            let i = at % bad.len();
            bad[i] ^= flip;
            prop_assert!(key.open(Kind::Sample, &bad).is_err());
        }

        /// Opening never panics, whatever the bytes.
        #[test]
        fn opening_arbitrary_bytes_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..128)) {
            let _ = secret().device("aero-1").open(Kind::Command, &bytes);
        }
    }
}
