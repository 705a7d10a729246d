//! What a plant's server holds, for a user writing its map: a range of a Modbus server's
//! registers read once and shown every way a map could read it ([`modbus`]), and an OPC UA
//! server's address space browsed ([`opcua`]).

use std::fmt::Write as _;
use std::time::Duration;

use crate::opcua::SessionSpec;
use plant::modbus::{
    Point, RegisterKind, ValueType, WordOrder, MAX_BITS_PER_READ, MAX_REGISTERS_PER_READ,
};
use tokio_modbus::client::sync::{self, Client};
use tokio_modbus::{Request, Response, Slave};

/// A probe that could not be done.
#[derive(Debug, thiserror::Error)]
pub enum ProbeError {
    /// No connection, or the link failed.
    #[error("{address}: {message}")]
    Link {
        /// The server.
        address: String,
        /// What failed.
        message: String,
    },
    /// The server answered with an exception (an address it does not have, ...).
    #[error("{address}: {kind:?} {start}..{end}: {message}")]
    Refused {
        /// The server.
        address: String,
        /// What was asked.
        kind: RegisterKind,
        /// First address.
        start: u16,
        /// Past the last.
        end: u32,
        /// The server's answer.
        message: String,
    },
    /// Nothing to read, or more than one request may carry.
    #[error("count must be 1 to {0}")]
    Count(u16),
}

/// Read `count` values of `kind` from `start` on unit `unit` of `address`, and render
/// them: for bits one line each; for registers each as int16/uint16 and each pair as
/// (u)int32 and float32 in both word orders.
pub fn modbus(
    address: &str,
    unit: u8,
    kind: RegisterKind,
    start: u16,
    count: u16,
    timeout: Duration,
) -> Result<String, ProbeError> {
    let words = read_words(address, unit, kind, start, count, timeout)?;
    Ok(render(kind, start, &words))
}

/// The value of `point` on unit `unit` of `address` now, as a map would read it (`None`
/// if it is not a finite number).
pub fn read_point(
    address: &str,
    unit: u8,
    point: &Point,
    timeout: Duration,
) -> Result<Option<f64>, ProbeError> {
    let words = read_words(
        address,
        unit,
        point.kind,
        point.address,
        point.width(),
        timeout,
    )?;
    Ok(point.decode(&words))
}

fn read_words(
    address: &str,
    unit: u8,
    kind: RegisterKind,
    start: u16,
    count: u16,
    timeout: Duration,
) -> Result<Vec<u16>, ProbeError> {
    let max = if kind.is_bit() {
        MAX_BITS_PER_READ
    } else {
        MAX_REGISTERS_PER_READ
    };
    if count == 0 || count > max || u32::from(start) + u32::from(count) > 65536 {
        return Err(ProbeError::Count(max));
    }
    let link = |e: &dyn std::fmt::Display| ProbeError::Link {
        address: address.into(),
        message: e.to_string(),
    };
    let addr = std::net::ToSocketAddrs::to_socket_addrs(address)
        .map_err(|e| link(&e))?
        .next()
        .ok_or_else(|| link(&"no address"))?;
    let mut ctx = sync::tcp::connect_slave_with_timeout(addr, Slave(unit), Some(timeout))
        .map_err(|e| link(&e))?;
    ctx.set_timeout(timeout);
    let request = match kind {
        RegisterKind::Coil => Request::ReadCoils(start, count),
        RegisterKind::DiscreteInput => Request::ReadDiscreteInputs(start, count),
        RegisterKind::Input => Request::ReadInputRegisters(start, count),
        RegisterKind::Holding => Request::ReadHoldingRegisters(start, count),
    };
    let refused = |message: String| ProbeError::Refused {
        address: address.into(),
        kind,
        start,
        end: u32::from(start) + u32::from(count),
        message,
    };
    let words: Vec<u16> = match ctx.call(request) {
        Ok(Ok(Response::ReadCoils(b) | Response::ReadDiscreteInputs(b))) => {
            b.into_iter().map(u16::from).collect()
        }
        Ok(Ok(Response::ReadInputRegisters(w) | Response::ReadHoldingRegisters(w))) => w,
        Ok(Ok(other)) => return Err(refused(format!("answered {other:?}"))),
        Ok(Err(exception)) => return Err(refused(format!("exception {exception}"))),
        Err(e) => return Err(link(&e)),
    };
    if words.len() < usize::from(count) {
        return Err(refused(format!("answered {} values", words.len())));
    }
    Ok(words[..usize::from(count)].to_vec())
}

/// The table [`modbus`] prints.
pub fn render(kind: RegisterKind, start: u16, words: &[u16]) -> String {
    let mut out = String::new();
    if kind.is_bit() {
        let _ = writeln!(out, "{kind:?} address  value");
        for (i, w) in words.iter().enumerate() {
            let _ = writeln!(out, "{:>16}  {}", usize::from(start) + i, w);
        }
        return out;
    }
    let _ = writeln!(
        out,
        "{:>7}  {:>6}  {:>6}  {:>6}  | {:>12} {:>12} {:>14} {:>14}",
        "address",
        "hex",
        "uint16",
        "int16",
        "int32 big",
        "int32 little",
        "float32 big",
        "float32 little"
    );
    let as_point = |t: ValueType, order: WordOrder| Point {
        kind,
        address: 0,
        value_type: Some(t),
        word_order: order,
        scale: 1.0,
        offset: 0.0,
    };
    let show = |p: Point, pair: &[u16]| match (p.decode(pair), p.value_type()) {
        (None, _) => "-".to_string(),
        (Some(v), ValueType::Float32) => compact(v),
        (Some(v), _) => format!("{v}"),
    };
    for (i, &w) in words.iter().enumerate() {
        let _ = write!(
            out,
            "{:>7}  {w:#06x}  {w:>6}  {:>6}  |",
            usize::from(start) + i,
            w as i16
        );
        if let Some(pair) = words.get(i..i + 2) {
            let _ = write!(
                out,
                " {:>12} {:>12} {:>14} {:>14}",
                show(as_point(ValueType::Int32, WordOrder::Big), pair),
                show(as_point(ValueType::Int32, WordOrder::Little), pair),
                show(as_point(ValueType::Float32, WordOrder::Big), pair),
                show(as_point(ValueType::Float32, WordOrder::Little), pair),
            );
        }
        out.push('\n');
    }
    out
}

/// A float as a person reads it: its f32 digits, in exponent form when very large or small.
fn compact(v: f64) -> String {
    let f = v as f32;
    if f != 0.0 && !(1e-4..1e7).contains(&f.abs()) {
        format!("{f:e}")
    } else {
        format!("{f}")
    }
}

/// What an OPC UA server's address space holds under `start` (a node id; the Objects
/// folder by default), `depth` levels down: each node's id, browse name and class, and for
/// a variable its value's type and value, so that a user finds the node ids to map.
pub fn opcua(spec: &SessionSpec, start: &str, depth: usize) -> Result<String, ProbeError> {
    let link = |message: String| ProbeError::Link {
        address: spec.endpoint.clone(),
        message,
    };
    let timeout = spec.request_timeout;
    let start: opcua::types::NodeId = start
        .parse()
        .map_err(|_| link(format!("{start:?} is not a node id")))?;
    let (rt, session, _) = crate::opcua::open_session(spec).map_err(link)?;
    let mut out = String::new();
    let walked = rt.block_on(walk(&session, start, depth, timeout, &mut out));
    rt.block_on(async {
        let _ = tokio::time::timeout(timeout, session.disconnect()).await;
    });
    drop(rt);
    walked.map_err(link)?;
    Ok(out)
}

/// The most nodes a probe walks, and the most browse rounds (continuation points) per
/// node: a server answers what it likes.
const MAX_NODES: usize = 5000;
const MAX_ROUNDS: usize = 100;

/// Every hierarchical reference of `node`, following continuation points (at most
/// `MAX_ROUNDS`).
async fn browse_all(
    session: &opcua::client::Session,
    node: opcua::types::NodeId,
    timeout: Duration,
) -> Result<Vec<opcua::types::ReferenceDescription>, String> {
    use opcua::types::{
        BrowseDescription, BrowseDirection, BrowseResultMask, NodeClassMask, ReferenceTypeId,
    };
    let desc = BrowseDescription {
        node_id: node,
        browse_direction: BrowseDirection::Forward,
        reference_type_id: ReferenceTypeId::HierarchicalReferences.into(),
        include_subtypes: true,
        node_class_mask: NodeClassMask::all().bits(),
        result_mask: BrowseResultMask::All as u32,
    };
    let first = |r: Vec<opcua::types::BrowseResult>| {
        r.into_iter()
            .next()
            .ok_or_else(|| "browse: the server answered no result".to_string())
    };
    let mut res = first(
        tokio::time::timeout(timeout, session.browse(&[desc], 0, None))
            .await
            .map_err(|_| "browse: timed out".to_string())?
            .map_err(|e| format!("browse: {e}"))?,
    )?;
    let mut refs = Vec::new();
    for _ in 0..MAX_ROUNDS {
        refs.extend(res.references.take().unwrap_or_default());
        if res.continuation_point.is_null() || res.status_code.is_bad() {
            return Ok(refs);
        }
        let point = [res.continuation_point.clone()];
        let next = session.browse_next(false, &point);
        res = first(
            tokio::time::timeout(timeout, next)
                .await
                .map_err(|_| "browse: timed out".to_string())?
                .map_err(|e| format!("browse: {e}"))?,
        )?;
    }
    Ok(refs)
}

/// Browse `node`'s hierarchical children, line by line into `out`, down to `depth`.
async fn walk(
    session: &opcua::client::Session,
    node: opcua::types::NodeId,
    depth: usize,
    timeout: Duration,
    out: &mut String,
) -> Result<(), String> {
    use opcua::types::{AttributeId, NodeClass, ReadValueId, TimestampsToReturn};
    // Iterative, depth first: (node, level); each node once (an address space may have
    // cycles), and at most MAX_NODES lines (a server may be huge, or hostile).
    let mut seen = std::collections::HashSet::new();
    let mut stack = vec![(node, 0usize)];
    while let Some((node, level)) = stack.pop() {
        if level >= depth || !seen.insert(node.clone()) {
            continue;
        }
        if seen.len() > MAX_NODES {
            let _ = writeln!(
                out,
                "... (stopped after {MAX_NODES} nodes: narrow --node or --depth)"
            );
            break;
        }
        let refs = browse_all(session, node, timeout).await?;
        let mut children = Vec::new();
        for r in refs {
            let id = r.node_id.node_id.clone();
            let mut line = format!(
                "{:indent$}{id}  {}  {:?}",
                "",
                r.browse_name.name,
                r.node_class,
                indent = 2 * level
            );
            if r.node_class == NodeClass::Variable {
                let read = [ReadValueId::new(id.clone(), AttributeId::Value)];
                let v = tokio::time::timeout(
                    timeout,
                    session.read(&read, TimestampsToReturn::Neither, 0.0),
                )
                .await
                .map_err(|_| "read: timed out".to_string())?
                .map_err(|e| format!("read: {e}"))?;
                match v.first().and_then(|dv| dv.value.as_ref()) {
                    Some(value) if !matches!(value, opcua::types::Variant::Empty) => {
                        let t = value
                            .scalar_type_id()
                            .map_or("?".to_string(), |t| format!("{t:?}"));
                        let mut shown = value.to_string();
                        if shown.chars().count() > 60 {
                            shown = shown.chars().take(57).collect::<String>() + "...";
                        }
                        let _ = write!(line, "  {t} = {shown}");
                    }
                    _ => line.push_str("  (empty)"),
                }
            }
            out.push_str(&line);
            out.push('\n');
            children.push((id, level + 1));
        }
        // Depth first, in the server's order.
        stack.extend(children.into_iter().rev());
    }
    Ok(())
}

/// The value of node `node` on `endpoint` now, if it is a finite number.
pub fn read_node(spec: &SessionSpec, node: &str) -> Result<Option<f64>, ProbeError> {
    let link = |message: String| ProbeError::Link {
        address: spec.endpoint.clone(),
        message,
    };
    let timeout = spec.request_timeout;
    let id: opcua::types::NodeId = node
        .parse()
        .map_err(|_| link(format!("{node:?} is not a node id")))?;
    let (rt, session, _) = crate::opcua::open_session(spec).map_err(link)?;
    let read = [opcua::types::ReadValueId::new_value(id)];
    let value = rt.block_on(async {
        let v = tokio::time::timeout(
            timeout,
            session.read(&read, opcua::types::TimestampsToReturn::Neither, 0.0),
        )
        .await;
        let _ = tokio::time::timeout(timeout, session.disconnect()).await;
        v
    });
    drop(rt);
    let values = value
        .map_err(|_| link("read: timed out".into()))?
        .map_err(|e| link(format!("read: {e}")))?;
    Ok(values.first().and_then(crate::opcua::number))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_float_shows_in_the_word_order_it_was_written_in() {
        // 21.5f32 = 0x41AC_0000, high word first.
        let t = render(RegisterKind::Holding, 100, &[0x41AC, 0x0000, 7]);
        let first = t.lines().nth(1).unwrap();
        assert!(first.starts_with("    100  0x41ac"), "{first}");
        assert!(first.contains(" 21.5 "), "{first}");
        assert_eq!(t.lines().count(), 4, "a header and three registers");
        let bits = render(RegisterKind::Coil, 0, &[1, 0]);
        assert!(bits.contains("               0  1\n"), "{bits}");
    }
}
