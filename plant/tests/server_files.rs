//! Plant files of plants behind a server (Modbus, OPC UA) as the loader reads them: the
//! map is checked against the file's channels (their count and actuator ranges) and named
//! field by field when it is wrong; the offline runner refuses the plant with a reason.

use plant::scenario::{load_scenario, PlantSource, ScenarioError};

const CHANNEL: &str = r#"
[[channels]]
name = "temperature"
reference = [{ kind = "constant", value = 20.0 }]
output = { min = 0.0, max = 24.0 }
"#;

fn file(plant: &str, channels: usize) -> Result<plant::scenario::Scenario, ScenarioError> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.toml");
    let mut text = format!(
        "name = \"m\"\nduration = 10.0\nperiod = 0.1\n\
         controller = {{ name = \"ip\", channels = [{}] }}\n{plant}\n",
        vec![
            "{ law = \"intelligent\", params = { kind = \"ip\", alpha = 0.1, kp = 1.0 } }";
            channels
        ]
        .join(", ")
    );
    for i in 0..channels {
        text.push_str(&CHANNEL.replace("temperature", &format!("t{i}")));
    }
    std::fs::write(&path, text).unwrap();
    load_scenario(path.to_str().unwrap())
}

const MAP: &str = r#"
[plant.modbus]
address = "127.0.0.1:5020"
[[plant.modbus.channels]]
output = { kind = "input", address = 0, type = "float32" }
input = { kind = "holding", address = 0, type = "int16", scale = 0.01 }
safe = 1.5
"#;

fn field(e: ScenarioError) -> String {
    match e {
        ScenarioError::Invalid { field, .. } => field,
        other => panic!("expected an invalid field, got {other}"),
    }
}

#[test]
fn a_modbus_map_loads_with_its_timeout_and_safe_inputs() {
    let s = file(MAP, 1).unwrap();
    let PlantSource::Modbus(m) = &s.plant else {
        panic!("a Modbus plant")
    };
    assert_eq!(m.timeout.as_millis(), 50, "half the 0.1 s period");
    assert_eq!(m.config.unit, 1);
    assert_eq!(s.safe_inputs(), vec![1.5]);
    let e = plant::open(&s.plant, 1, 1).err().expect("offline refused");
    assert!(
        e.to_string().contains("real time through plant-agent"),
        "{e}"
    );
}

#[test]
fn a_wrong_map_is_refused_with_its_field() {
    let outside = MAP.replace("safe = 1.5", "safe = 30.0");
    assert_eq!(
        field(file(&outside, 1).unwrap_err()),
        "plant.modbus.channels[0].safe"
    );
    assert_eq!(field(file(MAP, 2).unwrap_err()), "plant.modbus.channels");
    let read_only = MAP.replace("input = { kind = \"holding\"", "input = { kind = \"input\"");
    assert_eq!(
        field(file(&read_only, 1).unwrap_err()),
        "plant.modbus.channels[0].input.kind"
    );
    let with_driver = MAP.replace(
        "[plant.modbus]",
        "[plant]\ndriver = [\"python3\"]\n[plant.modbus]",
    );
    assert_eq!(field(file(&with_driver, 1).unwrap_err()), "plant.modbus");
    // A field that is not in the map is a parse error naming it.
    let typo = MAP.replace("address = \"127", "unit_id = 3\naddress = \"127");
    match file(&typo, 1).unwrap_err() {
        ScenarioError::Parse { message, .. } => assert!(message.contains("unit_id"), "{message}"),
        other => panic!("expected a parse error, got {other}"),
    }
}

const OPCUA: &str = r#"
[plant.opcua]
endpoint = "opc.tcp://127.0.0.1:4840/"
user = "operator"
password_file = "pw"
[[plant.opcua.channels]]
output = "ns=2;s=Plant.Output"
input = "ns=2;i=1002"
safe = 2.0
"#;

/// The scenario `plant` with a password file `pw` beside it (if `password` is given).
fn file_with_password(
    plant: &str,
    password: Option<&str>,
) -> Result<plant::scenario::Scenario, ScenarioError> {
    let dir = tempfile::tempdir().unwrap();
    if let Some(p) = password {
        std::fs::write(dir.path().join("pw"), format!("{p}\nignored second line\n")).unwrap();
    }
    let path = dir.path().join("s.toml");
    std::fs::write(&path, scenario_text(plant)).unwrap();
    load_scenario(path.to_str().unwrap())
}

/// A one-channel scenario at 100 Hz around `plant`.
fn scenario_text(plant: &str) -> String {
    format!(
        "name = \"o\"\nduration = 10.0\nperiod = 0.01\n\
         controller = {{ name = \"ip\", channels = [{{ law = \"intelligent\", params = {{ kind = \"ip\", alpha = 0.1, kp = 1.0 }} }}] }}\n\
         {plant}\n{CHANNEL}"
    )
}

#[test]
fn an_opcua_map_loads_with_its_password_and_never_prints_it() {
    let s = file_with_password(OPCUA, Some("s3cret")).unwrap();
    let PlantSource::OpcUa(o) = &s.plant else {
        panic!("an OPC UA plant")
    };
    assert_eq!(
        o.password.as_deref(),
        Some("s3cret"),
        "the file's first line"
    );
    assert_eq!(o.timeout.as_millis(), 20, "half of 10 ms, at least 20");
    assert_eq!(s.safe_inputs(), vec![2.0]);
    let printed = format!("{:?}", s.plant);
    assert!(!printed.contains("s3cret"), "{printed}");
    let e = plant::open(&s.plant, 1, 1).err().expect("offline refused");
    assert!(e.to_string().contains("OPC UA server"), "{e}");
    // No password file: a clear error naming it.
    match file_with_password(OPCUA, None).unwrap_err() {
        ScenarioError::Io { file, .. } => assert!(file.ends_with("pw"), "{file:?}"),
        other => panic!("expected the missing password file, got {other}"),
    }
    let bad = OPCUA.replace("ns=2;i=1002", "Plant.Input");
    assert_eq!(
        field(file_with_password(&bad, Some("x")).unwrap_err()),
        "plant.opcua.channels[0].input"
    );
    let secured = OPCUA.replace(
        "[plant.opcua]\n",
        "[plant.opcua]\nsecurity_policy = \"Basic256Sha256\"\n",
    );
    assert_eq!(
        field(file_with_password(&secured, Some("x")).unwrap_err()),
        "plant.opcua.security_mode",
        "a policy without its mode"
    );
    // Signed and encrypted, the user a certificate: the paths resolved beside the file,
    // and a certificate that is not there named.
    let secured = OPCUA.replace("user = \"operator\"\npassword_file = \"pw\"\n", "").replace(
        "[plant.opcua]\n",
        "[plant.opcua]\nsecurity_policy = \"Basic256Sha256\"\nsecurity_mode = \"SignAndEncrypt\"\n\
         pki_dir = \"pki\"\nuser_certificate = \"user.der\"\nuser_private_key = \"user.pem\"\n",
    );
    assert_eq!(
        field(file_with_password(&secured, None).unwrap_err()),
        "plant.opcua.user_certificate"
    );
    let dir = tempfile::tempdir().unwrap();
    for f in ["user.der", "user.pem"] {
        std::fs::write(dir.path().join(f), "x").unwrap();
    }
    let path = dir.path().join("s.toml");
    std::fs::write(&path, scenario_text(&secured)).unwrap();
    let s = load_scenario(path.to_str().unwrap()).unwrap();
    let PlantSource::OpcUa(o) = &s.plant else {
        panic!("an OPC UA plant")
    };
    assert_eq!(o.pki_dir.as_deref(), Some(dir.path().join("pki").as_path()));
    let (cert, key) = o.user_certificate.clone().unwrap();
    assert_eq!(
        (cert, key),
        (dir.path().join("user.der"), dir.path().join("user.pem"))
    );
    assert_eq!(o.password, None);
}
