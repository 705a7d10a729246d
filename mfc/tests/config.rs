//! Configurations read from TOML, as the service and the scenario files will.

use mfc::{ChannelConfig, ControllerKind, EstimatorKind, LawConfig, Order};

#[test]
fn channel_config_from_toml() {
    let text = r#"
        [law]
        law = "intelligent"
        params = { kind = "ipd", order = "two", alpha = 5.0, kp = 25.0, kd = 10.0 }
        estimator = { kind = { kind = "low_pass", time_constant = 0.05 }, window = 20 }

        [output]
        dead_zone = 10.0
        min = -24.0
        max = 24.0
    "#;
    let cfg: ChannelConfig = toml::from_str(text).unwrap();
    let LawConfig::Intelligent { params, estimator } = cfg.law else {
        panic!("not intelligent");
    };
    assert_eq!(params.kind, ControllerKind::PD);
    assert_eq!(params.order, Order::Two);
    assert_eq!(
        params.ki, 0.0,
        "omitted fields take their documented defaults"
    );
    assert_eq!(estimator.window, 20);
    assert_eq!(
        estimator.kind,
        EstimatorKind::LowPass {
            time_constant: 0.05
        }
    );
    assert_eq!(cfg.output.max, 24.0);
    mfc::Channel::<256>::new(&cfg).unwrap();
}

#[test]
fn unknown_fields_are_refused() {
    for text in [
        "[law]\nlaw = \"pid\"\nparams = { kp = 1.0, kpp = 2.0 }",
        "[law]\nlaw = \"intelligent\"\nalpha = 2.0",
        "[output]\ndeadzone = 10.0",
        "[law]\nlaw = \"fuzzy\"",
    ] {
        let err = toml::from_str::<ChannelConfig>(text)
            .unwrap_err()
            .to_string();
        assert!(err.contains("unknown"), "{text}: {err}");
    }
}
