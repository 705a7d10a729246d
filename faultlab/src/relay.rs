//! The impairment relay: a user-space forwarder between Zenoh endpoints that loses, delays,
//! jitters, reorders, duplicates, rate-limits and cuts traffic, per direction, from a
//! seeded generator. This kernel has no netem; the relay needs no privileges and runs
//! anywhere.
//!
//! Plants connect to the relay's address instead of the controller's; the relay forwards
//! to the controller. "Up" is plant -> controller (samples), "down" is controller -> plant
//! (commands).

use std::collections::{BinaryHeap, HashMap};
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use rand_xoshiro::rand_core::{Rng as _, SeedableRng};
use rand_xoshiro::Xoshiro256StarStar;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream, UdpSocket};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::Instant;

use crate::profile::{Impairment, Profile};

/// Which transport the relay forwards.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum,
)]
#[serde(rename_all = "lowercase")]
pub enum Link {
    /// Datagrams: each packet is impaired on its own.
    Udp,
    /// A byte stream: loss becomes retransmission delay, order is kept.
    Tcp,
}

impl Link {
    /// The zenoh endpoint prefix: plants reach the relay at `{scheme}/{listen}`.
    pub fn scheme(self) -> &'static str {
        match self {
            Link::Udp => "udp",
            Link::Tcp => "tcp",
        }
    }
}

/// Counters of one direction. They count every packet, zenoh's own session traffic
/// included, and also before the relay is armed.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DirectionStats {
    /// Packets (UDP) or chunks (TCP: what one read returned, not segments) received,
    /// whatever their fate.
    pub received: u64,
    /// Dropped by loss (UDP) or held back by a retransmission timeout (TCP).
    pub lost: u64,
    /// Dropped (UDP) or held (TCP) by an outage.
    pub outage: u64,
    /// Packets sent twice (UDP only; the copy follows 0.5 ms later).
    pub duplicated: u64,
    /// Packets held back by `reorder_ms` (UDP only); not those that jitter alone reorders.
    pub reordered: u64,
    /// Bytes let through: a duplicated packet counts once, dropped packets not at all.
    pub bytes: u64,
}

/// Counters of both directions.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RelayStats {
    /// Plant -> controller.
    pub up: DirectionStats,
    /// Controller -> plant.
    pub down: DirectionStats,
}

/// The fate of one packet.
#[derive(Debug, Clone, PartialEq)]
pub enum Fate {
    /// Never forwarded: lost, or cut by an outage.
    Drop,
    /// Sent at these instants (two for a duplicate).
    Send(Vec<Instant>),
}

/// The impairment state of one direction.
#[derive(Debug)]
pub struct Shaper {
    /// Until armed, traffic passes untouched (so sessions can establish; zenoh does not
    /// retransmit declarations lost on a UDP link). Arming starts the outage clock.
    armed: Arc<Mutex<Option<Instant>>>,
    imp: Impairment,
    rng: Uniform,
    /// Whether the Gilbert-Elliott chain is in its bad state.
    bad: bool,
    /// Creation time: the outage clock's origin when no arming time is set.
    start: Instant,
    /// When the rate-limited link is done sending what it already took.
    link_free: Instant,
    /// Latest release time given to a TCP chunk; no later chunk is released before it, so
    /// the stream keeps its order.
    last_release: Instant,
    /// Shared with the [`Relay`], which reads it for [`Relay::stats`].
    stats: Arc<Mutex<DirectionStats>>,
}

impl Shaper {
    /// A shaper for `imp`, seeded, armed at `start` (so the outage clock starts there) unless
    /// [`Shaper::with_arming`] gives it a shared switch instead.
    pub fn new(
        imp: Impairment,
        seed: u64,
        start: Instant,
        stats: Arc<Mutex<DirectionStats>>,
    ) -> Self {
        Self {
            armed: Arc::new(Mutex::new(Some(start))),
            imp,
            rng: Uniform(Xoshiro256StarStar::seed_from_u64(seed)),
            bad: false,
            start,
            link_free: start,
            last_release: start,
            stats,
        }
    }

    /// Share an arming switch (None: not armed yet; Some(t): armed at t).
    pub fn with_arming(mut self, armed: Arc<Mutex<Option<Instant>>>) -> Self {
        self.armed = armed;
        self
    }

    fn armed_at(&self) -> Option<Instant> {
        *self.armed.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn in_outage(&self, now: Instant) -> Option<Instant> {
        let start = self.armed_at().unwrap_or(self.start);
        let t = now.saturating_duration_since(start).as_secs_f64();
        self.imp
            .outages
            .iter()
            .find(|o| t >= o.start_s && t < o.start_s + o.duration_s)
            .map(|o| start + Duration::from_secs_f64(o.start_s + o.duration_s))
    }

    fn lost(&mut self) -> bool {
        match self.imp.burst {
            Some(ge) => {
                let flip = self.rng.uniform();
                self.bad = if self.bad {
                    flip >= ge.p_bad_good
                } else {
                    flip < ge.p_good_bad
                };
                let p = if self.bad { ge.loss_bad } else { ge.loss_good };
                self.rng.uniform() < p
            }
            None => self.imp.loss > 0.0 && self.rng.uniform() < self.imp.loss,
        }
    }

    fn delay(&mut self) -> Duration {
        let j = self.imp.jitter_ms;
        let jitter = if j > 0.0 {
            (self.rng.uniform() * 2.0 - 1.0) * j
        } else {
            0.0
        };
        Duration::from_secs_f64(((self.imp.delay_ms + jitter) / 1000.0).max(0.0))
    }

    fn rate(&mut self, now: Instant, len: usize) -> Instant {
        match self.imp.rate_kbps {
            Some(kbps) => {
                let at = self.link_free.max(now);
                self.link_free = at + Duration::from_secs_f64(len as f64 * 8.0 / (kbps * 1000.0));
                at
            }
            None => now,
        }
    }

    /// What happens to a datagram of `len` bytes received `now`.
    pub fn datagram(&mut self, now: Instant, len: usize) -> Fate {
        let mut st = self.stats.lock().unwrap_or_else(|e| e.into_inner());
        st.received += 1;
        if self.armed_at().is_none() {
            st.bytes += len as u64;
            return Fate::Send(vec![now]);
        }
        if self.in_outage(now).is_some() {
            st.outage += 1;
            return Fate::Drop;
        }
        drop(st);
        if self.lost() {
            self.stats.lock().unwrap_or_else(|e| e.into_inner()).lost += 1;
            return Fate::Drop;
        }
        let mut at = self.rate(now, len) + self.delay();
        let mut st = self.stats.lock().unwrap_or_else(|e| e.into_inner());
        if self.imp.reorder > 0.0 && self.rng.uniform() < self.imp.reorder {
            at += Duration::from_secs_f64(self.imp.reorder_ms / 1000.0);
            st.reordered += 1;
        }
        st.bytes += len as u64;
        if self.imp.duplicate > 0.0 && self.rng.uniform() < self.imp.duplicate {
            st.duplicated += 1;
            return Fate::Send(vec![at, at + Duration::from_micros(500)]);
        }
        Fate::Send(vec![at])
    }

    /// When a stream chunk of `len` bytes received `now` may be written: in order, after the
    /// delay, after a retransmission timeout if "lost", after the end of an outage.
    pub fn chunk(&mut self, now: Instant, len: usize) -> Instant {
        if self.armed_at().is_none() {
            let at = now.max(self.last_release);
            self.last_release = at;
            let mut st = self.stats.lock().unwrap_or_else(|e| e.into_inner());
            st.received += 1;
            st.bytes += len as u64;
            return at;
        }
        let mut at = self.rate(now, len) + self.delay();
        let after_outage = self.delay();
        let stats = self.stats.clone();
        let mut st = stats.lock().unwrap_or_else(|e| e.into_inner());
        st.received += 1;
        st.bytes += len as u64;
        if let Some(end) = self.in_outage(now) {
            st.outage += 1;
            at = at.max(end + after_outage);
        }
        drop(st);
        if self.lost() {
            self.stats.lock().unwrap_or_else(|e| e.into_inner()).lost += 1;
            at += Duration::from_secs_f64(self.imp.tcp_rto_ms / 1000.0);
        }
        at = at.max(self.last_release);
        self.last_release = at;
        at
    }
}

/// A running relay; stops when dropped.
pub struct Relay {
    /// Address the plants connect to: the one asked for, with a port 0 replaced by the
    /// port actually bound.
    pub listen: SocketAddr,
    /// The arming switch both shapers share: `None` until armed.
    armed: Arc<Mutex<Option<Instant>>>,
    /// Counters of the up direction (plant -> controller).
    stats: Arc<Mutex<DirectionStats>>,
    /// Counters of the down direction (controller -> plant).
    stats_down: Arc<Mutex<DirectionStats>>,
    task: JoinHandle<()>,
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl Relay {
    /// Start relaying `link` traffic from `listen` to `target` under `profile`, impairing
    /// at once if `armed`, else only after [`Relay::arm`].
    pub async fn start(
        link: Link,
        listen: SocketAddr,
        target: SocketAddr,
        profile: &Profile,
        armed: bool,
    ) -> std::io::Result<Self> {
        let up_stats = Arc::new(Mutex::new(DirectionStats::default()));
        let down_stats = Arc::new(Mutex::new(DirectionStats::default()));
        let start = Instant::now();
        let arming = Arc::new(Mutex::new(armed.then_some(start)));
        let up = Shaper::new(profile.up().clone(), profile.seed, start, up_stats.clone())
            .with_arming(arming.clone());
        let down = Shaper::new(
            profile.down().clone(),
            profile
                .seed
                .wrapping_mul(0x9E37_79B9_7F4A_7C15)
                .wrapping_add(1),
            start,
            down_stats.clone(),
        )
        .with_arming(arming.clone());
        let (listen, task) = match link {
            Link::Udp => {
                let front = UdpSocket::bind(listen).await?;
                let addr = front.local_addr()?;
                (addr, tokio::spawn(udp_relay(front, target, up, down)))
            }
            Link::Tcp => {
                let listener = TcpListener::bind(listen).await?;
                let addr = listener.local_addr()?;
                (addr, tokio::spawn(tcp_relay(listener, target, up, down)))
            }
        };
        Ok(Self {
            listen,
            armed: arming,
            stats: up_stats,
            stats_down: down_stats,
            task,
        })
    }

    /// Start impairing now (outage times count from here). Once armed, a later call does
    /// nothing.
    pub fn arm(&self) {
        let mut a = self.armed.lock().unwrap_or_else(|e| e.into_inner());
        if a.is_none() {
            *a = Some(Instant::now());
        }
    }

    /// The counters so far.
    pub fn stats(&self) -> RelayStats {
        RelayStats {
            up: self.stats.lock().unwrap_or_else(|e| e.into_inner()).clone(),
            down: self
                .stats_down
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .clone(),
        }
    }
}

/// A UDP packet waiting in the relay's heap for its send time.
#[derive(Debug, PartialEq, Eq)]
struct Pending {
    at: Instant,
    /// Arrival rank: packets due at the same instant leave in the order they came.
    order: u64,
    /// Up (to the controller) rather than down (to the plant).
    to_server: bool,
    /// The plant's address: which uplink socket sends it up, or where it goes down.
    client: SocketAddr,
    bytes: Vec<u8>,
}

impl Ord for Pending {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        // Earliest first in a max-heap.
        other.at.cmp(&self.at).then(other.order.cmp(&self.order))
    }
}
impl PartialOrd for Pending {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

/// How long before a send time tokio's timer hands over to [`send_time`]'s blocking sleep.
const COARSE: Duration = Duration::from_micros(1500);

/// Wait until `at` to about 0.1 ms. tokio's timer counts whole milliseconds and rounds up,
/// and the reactor's `epoll_wait` rounds up again: a plain `sleep_until` wakes 1.3 ms late
/// at the median (2 ms at the 99th percentile, `cargo bench -p plant-agent --bench pace`
/// on a 2-core machine). A profile's fixed 45 ms each way measured a 92.4 ms round trip
/// through the agent (0.2 ms without the relay); with this wait, 90.5 ms. tokio's timer
/// sleeps until [`COARSE`] before `at`, then a thread of the blocking pool sleeps the
/// rest on the kernel's high-resolution timer (0.11 ms late at the median). The thread
/// only sleeps, for at most [`COARSE`]; a dropped wait leaves it to finish alone. (The
/// agent has the same wait in `plant_agent::pace`; this crate links no application
/// crate, so it keeps its own.)
async fn send_time(at: Instant) {
    if let Some(early) = at.checked_sub(COARSE) {
        if early > Instant::now() {
            tokio::time::sleep_until(early).await;
        }
    }
    let rest = at.saturating_duration_since(Instant::now());
    if !rest.is_zero() {
        let _ = tokio::task::spawn_blocking(move || std::thread::sleep(rest)).await;
    }
}

async fn udp_relay(front: UdpSocket, target: SocketAddr, mut up: Shaper, mut down: Shaper) {
    let front = Arc::new(front);
    let mut uplinks: HashMap<SocketAddr, Arc<UdpSocket>> = HashMap::new();
    let (back_tx, mut back_rx) = mpsc::channel::<(SocketAddr, Vec<u8>)>(4096);
    let mut heap: BinaryHeap<Pending> = BinaryHeap::new();
    let mut order = 0u64;
    let mut buf = vec![0u8; 65536];
    // The wait for the earliest send time, kept across packets that do not change it (a
    // new wait per arrival would start a blocking sleep per arrival near a send time).
    let mut timer: std::pin::Pin<Box<dyn std::future::Future<Output = ()> + Send>> =
        Box::pin(std::future::pending());
    let mut armed: Option<Instant> = None;
    loop {
        let next = heap.peek().map(|p| p.at);
        if next != armed {
            armed = next;
            timer = match next {
                Some(at) => Box::pin(send_time(at)),
                None => Box::pin(std::future::pending()),
            };
        }
        tokio::select! {
            r = front.recv_from(&mut buf) => {
                let Ok((len, client)) = r else { continue };
                if let std::collections::hash_map::Entry::Vacant(slot) = uplinks.entry(client) {
                    let Ok(sock) = UdpSocket::bind("127.0.0.1:0").await else { continue };
                    if sock.connect(target).await.is_err() { continue; }
                    let sock = Arc::new(sock);
                    let (reader, tx) = (sock.clone(), back_tx.clone());
                    tokio::spawn(async move {
                        let mut b = vec![0u8; 65536];
                        while let Ok(n) = reader.recv(&mut b).await {
                            if tx.send((client, b[..n].to_vec())).await.is_err() { break; }
                        }
                    });
                    slot.insert(sock);
                }
                let now = Instant::now();
                if let Fate::Send(times) = up.datagram(now, len) {
                    for at in times {
                        if at <= now {
                            // No delay: forward at once (a timer would add a millisecond).
                            if let Some(s) = uplinks.get(&client) {
                                let _ = s.send(&buf[..len]).await;
                            }
                            continue;
                        }
                        order += 1;
                        heap.push(Pending { at, order, to_server: true, client, bytes: buf[..len].to_vec() });
                    }
                }
            }
            Some((client, bytes)) = back_rx.recv() => {
                let now = Instant::now();
                if let Fate::Send(times) = down.datagram(now, bytes.len()) {
                    for at in times {
                        if at <= now {
                            let _ = front.send_to(&bytes, client).await;
                            continue;
                        }
                        order += 1;
                        heap.push(Pending { at, order, to_server: false, client, bytes: bytes.clone() });
                    }
                }
            }
            () = &mut timer => {
                // Spent: never polled again (an async fn panics when resumed after it
                // returned); the next loop arms a new one for the new earliest send time.
                timer = Box::pin(std::future::pending());
                armed = None;
                let now = Instant::now();
                while heap.peek().is_some_and(|p| p.at <= now) {
                    let Some(p) = heap.pop() else { break };
                    if p.to_server {
                        if let Some(s) = uplinks.get(&p.client) {
                            let _ = s.send(&p.bytes).await;
                        }
                    } else {
                        let _ = front.send_to(&p.bytes, p.client).await;
                    }
                }
            }
        }
    }
}

async fn tcp_relay(listener: TcpListener, target: SocketAddr, up: Shaper, down: Shaper) {
    // All connections share one shaper per direction (one link).
    let up = Arc::new(tokio::sync::Mutex::new(up));
    let down = Arc::new(tokio::sync::Mutex::new(down));
    loop {
        let Ok((client, _)) = listener.accept().await else {
            continue;
        };
        let Ok(server) = TcpStream::connect(target).await else {
            continue;
        };
        let _ = client.set_nodelay(true);
        let _ = server.set_nodelay(true);
        let (cr, cw) = client.into_split();
        let (sr, sw) = server.into_split();
        tokio::spawn(pump(cr, sw, up.clone()));
        tokio::spawn(pump(sr, cw, down.clone()));
    }
}

async fn pump(
    mut from: tokio::net::tcp::OwnedReadHalf,
    mut to: tokio::net::tcp::OwnedWriteHalf,
    shaper: Arc<tokio::sync::Mutex<Shaper>>,
) {
    let (tx, mut rx) = mpsc::unbounded_channel::<(Instant, Vec<u8>)>();
    let writer = tokio::spawn(async move {
        while let Some((at, bytes)) = rx.recv().await {
            if at > Instant::now() {
                send_time(at).await;
            }
            if to.write_all(&bytes).await.is_err() {
                break;
            }
        }
        let _ = to.shutdown().await;
    });
    let mut buf = vec![0u8; 65536];
    loop {
        match from.read(&mut buf).await {
            Ok(0) | Err(_) => break,
            Ok(n) => {
                let at = shaper.lock().await.chunk(Instant::now(), n);
                if tx.send((at, buf[..n].to_vec())).is_err() {
                    break;
                }
            }
        }
    }
    drop(tx);
    let _ = writer.await;
}

/// Seeded uniform draws in [0, 1) (xoshiro256**, top 53 bits): every impairment replays
/// from its profile's seed.
#[derive(Debug, Clone)]
struct Uniform(Xoshiro256StarStar);

impl Uniform {
    fn uniform(&mut self) -> f64 {
        (self.0.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}
