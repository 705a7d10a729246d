//! The impairment relay: the shaper's statistics (deterministic, no sockets), then real
//! UDP and TCP traffic through the relay on loopback.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use faultlab::profile::{GilbertElliott, Impairment, Outage, Profile, ProfileSet};
use faultlab::relay::{DirectionStats, Fate, Link, Relay, Shaper};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream, UdpSocket};
use tokio::time::Instant;

fn shaper(imp: Impairment, seed: u64) -> (Shaper, Instant) {
    let start = Instant::now();
    (
        Shaper::new(
            imp,
            seed,
            start,
            Arc::new(Mutex::new(DirectionStats::default())),
        ),
        start,
    )
}

/// Which of `n` packets, one per millisecond, get through.
fn pattern(imp: &Impairment, seed: u64, n: u32) -> Vec<bool> {
    let (mut s, start) = shaper(imp.clone(), seed);
    (0..n)
        .map(|k| {
            matches!(
                s.datagram(start + Duration::from_millis(u64::from(k)), 100),
                Fate::Send(_)
            )
        })
        .collect()
}

#[test]
fn random_loss_rate_and_replay() {
    let imp = Impairment {
        loss: 0.3,
        ..Default::default()
    };
    let a = pattern(&imp, 7, 20_000);
    let passed = a.iter().filter(|x| **x).count() as f64 / 20_000.0;
    assert!((passed - 0.7).abs() < 0.015, "{passed}");
    assert_eq!(a, pattern(&imp, 7, 20_000), "same seed, same losses");
    assert_ne!(a, pattern(&imp, 8, 20_000), "another seed, other losses");
}

#[test]
fn gilbert_elliott_loss_is_bursty_with_the_right_mean() {
    let ge = GilbertElliott {
        p_good_bad: 0.107,
        p_bad_good: 0.25,
        loss_good: 0.0,
        loss_bad: 1.0,
    };
    let imp = Impairment {
        burst: Some(ge),
        ..Default::default()
    };
    let a = pattern(&imp, 3, 50_000);
    let lost = a.iter().filter(|x| !**x).count() as f64 / 50_000.0;
    assert!(
        (lost - ge.mean_loss()).abs() < 0.02,
        "{lost} vs {}",
        ge.mean_loss()
    );
    // Mean length of a run of losses: 1 / p_bad_good = 4 (random loss would give 1.4).
    let mut runs = Vec::new();
    let mut run = 0;
    for ok in &a {
        if *ok {
            if run > 0 {
                runs.push(run);
            }
            run = 0;
        } else {
            run += 1;
        }
    }
    let mean = runs.iter().sum::<u32>() as f64 / runs.len() as f64;
    assert!((mean - 4.0).abs() < 0.3, "mean burst {mean}");
}

#[test]
fn delay_jitter_reorder_duplicate_outage() {
    let imp = Impairment {
        delay_ms: 20.0,
        jitter_ms: 5.0,
        reorder: 0.1,
        reorder_ms: 15.0,
        duplicate: 0.05,
        outages: vec![Outage {
            start_s: 1.0,
            duration_s: 0.5,
        }],
        ..Default::default()
    };
    let (mut s, start) = shaper(imp, 11);
    let (mut dups, mut reordered, mut dropped) = (0, 0, 0);
    for k in 0..3000u64 {
        let now = start + Duration::from_millis(k);
        match s.datagram(now, 100) {
            Fate::Drop => {
                dropped += 1;
                assert!(
                    (1000..1500).contains(&k),
                    "dropped outside the outage at {k} ms"
                );
            }
            Fate::Send(times) => {
                let d = (times[0] - now).as_secs_f64() * 1000.0;
                assert!((15.0 - 1e-6..=40.0 + 1e-6).contains(&d), "delay {d} ms");
                if d > 25.0 + 1e-6 {
                    reordered += 1;
                }
                if times.len() == 2 {
                    dups += 1;
                }
            }
        }
    }
    assert_eq!(dropped, 500, "exactly the outage");
    assert!((200..300).contains(&reordered), "{reordered}");
    assert!((80..170).contains(&dups), "{dups}");
}

#[test]
fn tcp_chunks_stay_in_order_and_loss_costs_a_retransmission() {
    let imp = Impairment {
        loss: 0.2,
        delay_ms: 5.0,
        jitter_ms: 4.0,
        ..Default::default()
    };
    let (mut s, start) = shaper(imp, 5);
    let mut last = start;
    let mut stalls = 0;
    for k in 0..1000u64 {
        let now = start + Duration::from_millis(10 * k);
        let at = s.chunk(now, 200);
        assert!(at >= last, "order kept");
        if at - now >= Duration::from_millis(200) {
            stalls += 1;
        }
        last = at;
    }
    assert!((150..260).contains(&stalls), "{stalls}");
}

#[test]
fn profiles_parse_and_bad_ones_name_the_field() {
    let set = ProfileSet::load("default").unwrap();
    assert!(set.profiles.len() >= 10);
    assert!(set.profiles.iter().any(|p| !p.both.outages.is_empty()));
    let e = ProfileSet::parse(
        "p.toml",
        "[[profiles]]\nname = \"x\"\nboth = { loss = 1.5 }",
    )
    .unwrap_err();
    assert!(
        e.to_string().contains("p.toml") && e.to_string().contains("both.loss"),
        "{e}"
    );
    let e = ProfileSet::parse("p.toml", "[[profiles]]\nname = \"x\"\nboth = { los = 0.1 }")
        .unwrap_err();
    assert!(e.to_string().contains("los"), "{e}");
}

fn profile(imp: Impairment) -> Profile {
    Profile {
        name: "t".into(),
        seed: 1,
        both: imp,
        up: None,
        down: None,
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn udp_through_the_relay() {
    let server = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let target = server.local_addr().unwrap();
    let relay = Relay::start(
        Link::Udp,
        "127.0.0.1:0".parse().unwrap(),
        target,
        &profile(Impairment {
            loss: 0.25,
            delay_ms: 10.0,
            ..Default::default()
        }),
        true,
    )
    .await
    .unwrap();
    // Echo server.
    tokio::spawn(async move {
        let mut b = [0u8; 1500];
        while let Ok((n, from)) = server.recv_from(&mut b).await {
            let _ = server.send_to(&b[..n], from).await;
        }
    });
    let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
    client.connect(relay.listen).await.unwrap();
    let mut got = 0;
    let mut rtts = Vec::new();
    for k in 0u32..200 {
        let sent = Instant::now();
        client.send(&k.to_be_bytes()).await.unwrap();
        let mut b = [0u8; 16];
        if let Ok(Ok(n)) =
            tokio::time::timeout(Duration::from_millis(40), client.recv(&mut b)).await
        {
            assert_eq!(&b[..n], &k.to_be_bytes(), "payload intact");
            got += 1;
            rtts.push(sent.elapsed());
        }
    }
    // A round trip survives both directions: 0.75^2 = 0.56.
    let rate = f64::from(got) / 200.0;
    assert!((0.45..0.67).contains(&rate), "{rate}");
    assert!(
        rtts.iter().all(|d| *d >= Duration::from_millis(20)),
        "two 10 ms delays"
    );
    let st = relay.stats();
    assert_eq!(st.up.received, 200);
    assert!(st.up.lost > 25 && st.down.lost > 10, "{st:?}");
}

#[tokio::test(flavor = "multi_thread")]
async fn tcp_through_the_relay_survives_loss_and_an_outage_intact() {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let target = listener.local_addr().unwrap();
    let relay = Relay::start(
        Link::Tcp,
        "127.0.0.1:0".parse().unwrap(),
        target,
        &profile(Impairment {
            loss: 0.1,
            delay_ms: 5.0,
            outages: vec![Outage {
                start_s: 0.3,
                duration_s: 0.4,
            }],
            ..Default::default()
        }),
        true,
    )
    .await
    .unwrap();
    let server = tokio::spawn(async move {
        let (mut s, _) = listener.accept().await.unwrap();
        let mut all = Vec::new();
        s.read_to_end(&mut all).await.unwrap();
        all
    });
    let mut c = TcpStream::connect(relay.listen).await.unwrap();
    let mut sent = Vec::new();
    let start = Instant::now();
    for k in 0u32..100 {
        let chunk: Vec<u8> = (0..50).map(|i| (k * 7 + i) as u8).collect();
        c.write_all(&chunk).await.unwrap();
        sent.extend_from_slice(&chunk);
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    c.shutdown().await.unwrap();
    let got = tokio::time::timeout(Duration::from_secs(10), server)
        .await
        .unwrap()
        .unwrap();
    assert_eq!(got, sent, "every byte, in order");
    assert!(start.elapsed() >= Duration::from_millis(1000));
    assert!(relay.stats().up.outage > 0);
}
