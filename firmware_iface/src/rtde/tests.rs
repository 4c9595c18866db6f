//! Golden byte vectors written from the RTDE guide's package layouts, and property round trips.

use super::*;
use proptest::prelude::*;

fn one(buf: &[u8]) -> RawPackage<'_> {
    let (raw, used) = split_package(buf).unwrap().unwrap();
    assert_eq!(used, buf.len(), "golden vector is exactly one package");
    raw
}

const V1: ProtocolVersion = ProtocolVersion::V1;
const V2: ProtocolVersion = ProtocolVersion::V2;

#[test]
fn golden_request_protocol_version() {
    let bytes = [0x00, 0x05, b'V', 0x00, 0x02];
    let m = HostMessage::RequestProtocolVersion(2);
    assert_eq!(m.encode(V1).unwrap(), bytes);
    assert_eq!(HostMessage::decode(V1, one(&bytes)).unwrap(), m);
    let reply = [0x00, 0x04, b'V', 0x01];
    let r = RobotMessage::ProtocolVersionAccepted(true);
    assert_eq!(r.encode(V1).unwrap(), reply);
    assert_eq!(RobotMessage::decode(V2, one(&reply)).unwrap(), r);
    let refused = [0x00, 0x04, b'V', 0x00];
    assert_eq!(
        RobotMessage::decode(V1, one(&refused)).unwrap(),
        RobotMessage::ProtocolVersionAccepted(false)
    );
}

#[test]
fn golden_controller_version() {
    assert_eq!(
        HostMessage::GetControllerVersion.encode(V2).unwrap(),
        [0, 3, b'v']
    );
    let bytes = [
        0x00, 0x13, b'v', 0, 0, 0, 3, 0, 0, 0, 15, 0, 0, 0, 7, 0, 0, 0x01, 0x06,
    ];
    let r = RobotMessage::ControllerVersion(ControllerVersion {
        major: 3,
        minor: 15,
        bugfix: 7,
        build: 262,
    });
    assert_eq!(r.encode(V2).unwrap(), bytes);
    assert_eq!(RobotMessage::decode(V1, one(&bytes)).unwrap(), r);
}

#[test]
fn golden_setup_outputs_v2_and_v1() {
    // v2: 125.0 Hz = 0x405F400000000000, then "timestamp,actual_q".
    let mut v2 = vec![0x00, 0x1d, b'O', 0x40, 0x5f, 0x40, 0, 0, 0, 0, 0];
    v2.extend_from_slice(b"timestamp,actual_q");
    let m = HostMessage::SetupOutputs {
        frequency: Some(125.0),
        names: vec!["timestamp".into(), "actual_q".into()],
    };
    assert_eq!(m.encode(V2).unwrap(), v2);
    assert_eq!(HostMessage::decode(V2, one(&v2)).unwrap(), m);
    // v1: no frequency.
    let mut v1 = vec![0x00, 0x15, b'O'];
    v1.extend_from_slice(b"timestamp,actual_q");
    let m1 = HostMessage::SetupOutputs {
        frequency: None,
        names: vec!["timestamp".into(), "actual_q".into()],
    };
    assert_eq!(m1.encode(V1).unwrap(), v1);
    assert_eq!(HostMessage::decode(V1, one(&v1)).unwrap(), m1);
    // Replies: v2 has the recipe id, v1 not.
    let mut r2 = vec![0x00, 0x13, b'O', 0x01];
    r2.extend_from_slice(b"DOUBLE,VECTOR6D");
    let reply = RobotMessage::SetupOutputs {
        recipe_id: Some(1),
        types: vec![
            FieldType::Type(DataType::Double),
            FieldType::Type(DataType::Vector6d),
        ],
    };
    assert_eq!(reply.encode(V2).unwrap(), r2);
    assert_eq!(RobotMessage::decode(V2, one(&r2)).unwrap(), reply);
    let mut r1 = vec![0x00, 0x12, b'O'];
    r1.extend_from_slice(b"DOUBLE,VECTOR6D");
    let reply1 = RobotMessage::SetupOutputs {
        recipe_id: None,
        types: reply_types(&reply),
    };
    assert_eq!(reply1.encode(V1).unwrap(), r1);
    assert_eq!(RobotMessage::decode(V1, one(&r1)).unwrap(), reply1);
}

fn reply_types(m: &RobotMessage) -> Vec<FieldType> {
    match m {
        RobotMessage::SetupOutputs { types, .. } | RobotMessage::SetupInputs { types, .. } => {
            types.clone()
        }
        _ => panic!("not a setup reply"),
    }
}

#[test]
fn trailing_empty_name_is_dropped_but_inner_empty_names_are_kept() {
    let mut b = vec![0x00, 0x00, b'O', 0x40, 0x5f, 0x40, 0, 0, 0, 0, 0];
    b.extend_from_slice(b"actual_q,robot_mode,");
    let n = b.len() as u16;
    b[..2].copy_from_slice(&n.to_be_bytes());
    match HostMessage::decode(V2, one(&b)).unwrap() {
        HostMessage::SetupOutputs { names, .. } => assert_eq!(names, ["actual_q", "robot_mode"]),
        other => panic!("{other:?}"),
    }
    let mut c = vec![0x00, 0x00, b'I'];
    c.extend_from_slice(b"a,,b");
    let n = c.len() as u16;
    c[..2].copy_from_slice(&n.to_be_bytes());
    match HostMessage::decode(V2, one(&c)).unwrap() {
        HostMessage::SetupInputs { names } => assert_eq!(names, ["a", "", "b"]),
        other => panic!("{other:?}"),
    }
}

#[test]
fn golden_setup_inputs_with_not_found_and_in_use() {
    let mut req = vec![0x00, 0x31, b'I'];
    req.extend_from_slice(b"input_int_register_24,input_double_register_24");
    let m = HostMessage::SetupInputs {
        names: vec![
            "input_int_register_24".into(),
            "input_double_register_24".into(),
        ],
    };
    assert_eq!(m.encode(V1).unwrap(), req);
    let mut rep = vec![0x00, 0x00, b'I', 0x00];
    rep.extend_from_slice(b"IN_USE,NOT_FOUND");
    let n = rep.len() as u16;
    rep[..2].copy_from_slice(&n.to_be_bytes());
    let r = RobotMessage::SetupInputs {
        recipe_id: 0,
        types: vec![FieldType::InUse, FieldType::NotFound],
    };
    assert_eq!(r.encode(V2).unwrap(), rep);
    assert_eq!(RobotMessage::decode(V1, one(&rep)).unwrap(), r);
}

#[test]
fn golden_start_pause() {
    assert_eq!(HostMessage::Start.encode(V2).unwrap(), [0, 3, b'S']);
    assert_eq!(HostMessage::Pause.encode(V1).unwrap(), [0, 3, b'P']);
    assert_eq!(
        RobotMessage::StartAccepted(true).encode(V2).unwrap(),
        [0, 4, b'S', 1]
    );
    assert_eq!(
        RobotMessage::decode(V2, one(&[0, 4, b'P', 1])).unwrap(),
        RobotMessage::PauseAccepted(true)
    );
    assert!(RobotMessage::decode(V2, one(&[0, 5, b'S', 1, 0])).is_err());
}

#[test]
fn golden_data_packages_v1_v2_both_directions() {
    // robot_mode INT32 7, actual_q VECTOR6D all 1.0 (0x3FF0000000000000).
    let layout = Layout::new(&[DataType::Int32, DataType::Vector6d]);
    let values = layout
        .encode_all(&[Value::Int32(7), Value::Vector6d([1.0; 6])])
        .unwrap();
    let mut expect_values = vec![0, 0, 0, 7];
    for _ in 0..6 {
        expect_values.extend_from_slice(&[0x3f, 0xf0, 0, 0, 0, 0, 0, 0]);
    }
    assert_eq!(values, expect_values);
    let mut v2 = vec![0x00, 0x38, b'U', 0x01];
    v2.extend_from_slice(&expect_values);
    let r = RobotMessage::DataPackage {
        recipe_id: Some(1),
        values: values.clone(),
    };
    assert_eq!(r.encode(V2).unwrap(), v2);
    assert_eq!(RobotMessage::decode(V2, one(&v2)).unwrap(), r);
    let (id, vals) = robot_to_host::borrow_data_package(V2, one(&v2)).unwrap();
    assert_eq!(id, Some(1));
    assert_eq!(layout.get_i32(vals, 0).unwrap(), 7);
    assert_eq!(layout.get_vec6(vals, 1).unwrap(), [1.0; 6]);
    // v1 robot data package: no recipe id.
    let mut v1 = vec![0x00, 0x37, b'U'];
    v1.extend_from_slice(&expect_values);
    let r1 = RobotMessage::DataPackage {
        recipe_id: None,
        values: values.clone(),
    };
    assert_eq!(r1.encode(V1).unwrap(), v1);
    assert_eq!(RobotMessage::decode(V1, one(&v1)).unwrap(), r1);
    // Host input data package: recipe id in both versions. INT32 -1 = FFFFFFFF.
    let h = HostMessage::DataPackage {
        recipe_id: 2,
        values: vec![0xff, 0xff, 0xff, 0xff],
    };
    assert_eq!(
        h.encode(V1).unwrap(),
        [0, 8, b'U', 2, 0xff, 0xff, 0xff, 0xff]
    );
    let lay = Layout::new(&[DataType::Int32]);
    assert_eq!(lay.get_i32(&[0xff, 0xff, 0xff, 0xff], 0).unwrap(), -1);
}

#[test]
fn golden_text_messages_v1_and_v2() {
    let t = TextMessage {
        message: "hi".into(),
        source: "sim".into(),
        level: 3,
    };
    let v2 = [0, 0x0b, b'M', 2, b'h', b'i', 3, b's', b'i', b'm', 3];
    assert_eq!(RobotMessage::Text(t.clone()).encode(V2).unwrap(), v2);
    assert_eq!(
        RobotMessage::decode(V2, one(&v2)).unwrap(),
        RobotMessage::Text(t.clone())
    );
    let v1 = [0, 6, b'M', 3, b'h', b'i'];
    let t1 = TextMessage {
        source: String::new(),
        ..t
    };
    assert_eq!(RobotMessage::Text(t1.clone()).encode(V1).unwrap(), v1);
    assert_eq!(
        HostMessage::decode(V1, one(&v1)).unwrap(),
        HostMessage::Text(t1)
    );
}

#[test]
fn every_type_string_is_exact() {
    let strings: Vec<&str> = DataType::ALL.iter().map(|t| t.as_str()).collect();
    assert_eq!(
        strings,
        [
            "BOOL",
            "UINT8",
            "UINT32",
            "UINT64",
            "INT32",
            "DOUBLE",
            "VECTOR3D",
            "VECTOR6D",
            "VECTOR6INT32",
            "VECTOR6UINT32"
        ]
    );
    assert_eq!(
        DataType::ALL.iter().map(|t| t.size()).sum::<usize>(),
        1 + 1 + 4 + 8 + 4 + 8 + 24 + 48 + 24 + 24
    );
    assert!(matches!(
        FieldType::parse("FLOAT"),
        Err(RtdeError::UnknownType { .. })
    ));
}

#[test]
fn framing_rejects_bad_sizes_and_waits_for_more() {
    assert_eq!(split_package(&[0, 5, b'V', 0]).unwrap(), None);
    assert_eq!(split_package(&[0]).unwrap(), None);
    assert!(matches!(
        split_package(&[0, 2, b'V']),
        Err(RtdeError::BadSize { size: 2 })
    ));
    let two = [0, 3, b'S', 0, 3, b'P'];
    let (a, n) = split_package(&two).unwrap().unwrap();
    assert_eq!((a.kind, n), (b'S', 3));
    assert!(matches!(
        HostMessage::decode(V2, one(&[0, 3, b'X'])),
        Err(RtdeError::UnknownPackage { kind: b'X' })
    ));
}

#[test]
fn names_over_limit_are_refused() {
    let long = vec!["x".repeat(1500), "y".repeat(600)];
    assert!(matches!(
        HostMessage::SetupInputs { names: long }.encode(V2),
        Err(RtdeError::NamesTooLong { .. })
    ));
    assert!(matches!(
        HostMessage::SetupInputs {
            names: vec!["a,b".into()]
        }
        .encode(V2),
        Err(RtdeError::BadName { .. })
    ));
}

#[test]
fn layout_checks_types_and_lengths() {
    let l = Layout::new(&[DataType::Double, DataType::Uint32]);
    assert_eq!(l.size(), 12);
    assert!(matches!(
        l.get_i32(&[0; 12], 1),
        Err(RtdeError::FieldType { index: 1, .. })
    ));
    assert!(matches!(
        l.get_f64(&[0; 11], 0),
        Err(RtdeError::PackageSize {
            expected: 12,
            got: 11
        })
    ));
    assert!(matches!(
        l.get(&[0; 12], 2),
        Err(RtdeError::FieldIndex { .. })
    ));
    assert!(matches!(
        Value::read(DataType::Bool, &[2]),
        Err(RtdeError::BadBool { value: 2 })
    ));
}

fn any_value() -> impl Strategy<Value = Value> {
    let f = any::<f64>().prop_filter("NaN never equals itself", |x| !x.is_nan());
    prop_oneof![
        any::<bool>().prop_map(Value::Bool),
        any::<u8>().prop_map(Value::Uint8),
        any::<u32>().prop_map(Value::Uint32),
        any::<u64>().prop_map(Value::Uint64),
        any::<i32>().prop_map(Value::Int32),
        f.clone().prop_map(Value::Double),
        prop::array::uniform3(f.clone()).prop_map(Value::Vector3d),
        prop::array::uniform6(f).prop_map(Value::Vector6d),
        prop::array::uniform6(any::<i32>()).prop_map(Value::Vector6Int32),
        prop::array::uniform6(any::<u32>()).prop_map(Value::Vector6Uint32),
    ]
}

fn any_name() -> impl Strategy<Value = String> {
    "[a-z_0-9]{1,30}"
}

fn any_version() -> impl Strategy<Value = ProtocolVersion> {
    prop_oneof![Just(V1), Just(V2)]
}

fn any_field_type() -> impl Strategy<Value = FieldType> {
    prop_oneof![
        Just(FieldType::NotFound),
        Just(FieldType::InUse),
        (0..DataType::ALL.len()).prop_map(|i| FieldType::Type(DataType::ALL[i])),
    ]
}

fn any_text() -> impl Strategy<Value = TextMessage> {
    ("[ -~]{0,60}", "[ -~]{0,20}", 0u8..4).prop_map(|(message, source, level)| TextMessage {
        message,
        source,
        level,
    })
}

proptest! {
    #[test]
    fn data_values_round_trip(values in prop::collection::vec(any_value(), 0..20)) {
        let types: Vec<DataType> = values.iter().map(Value::data_type).collect();
        let layout = Layout::new(&types);
        let bytes = layout.encode_all(&values).unwrap();
        prop_assert_eq!(bytes.len(), layout.size());
        prop_assert_eq!(layout.decode_all(&bytes).unwrap(), values);
    }

    #[test]
    fn host_messages_round_trip(
        version in any_version(),
        names in prop::collection::vec(any_name(), 0..30),
        freq in 1.0f64..500.0,
        id in any::<u8>(),
        payload in prop::collection::vec(any::<u8>(), 0..200),
        text in any_text(),
    ) {
        let frequency = (version == V2).then_some(freq);
        let mut text = text;
        if version == V1 { text.source.clear(); }
        for m in [
            HostMessage::RequestProtocolVersion(u16::from(id)),
            HostMessage::GetControllerVersion,
            HostMessage::SetupOutputs { frequency, names: names.clone() },
            HostMessage::SetupInputs { names: names.clone() },
            HostMessage::Start,
            HostMessage::Pause,
            HostMessage::DataPackage { recipe_id: id, values: payload.clone() },
            HostMessage::Text(text.clone()),
        ] {
            let bytes = m.encode(version).unwrap();
            let (raw, used) = split_package(&bytes).unwrap().unwrap();
            prop_assert_eq!(used, bytes.len());
            prop_assert_eq!(HostMessage::decode(version, raw).unwrap(), m);
        }
    }

    #[test]
    fn robot_messages_round_trip(
        version in any_version(),
        types in prop::collection::vec(any_field_type(), 0..30),
        id in any::<u8>(),
        vers in prop::array::uniform4(any::<u32>()),
        payload in prop::collection::vec(any::<u8>(), 0..200),
        text in any_text(),
        flag in any::<bool>(),
    ) {
        let rid = (version == V2).then_some(id);
        let mut text = text;
        if version == V1 { text.source.clear(); }
        for m in [
            RobotMessage::ProtocolVersionAccepted(flag),
            RobotMessage::ControllerVersion(ControllerVersion { major: vers[0], minor: vers[1], bugfix: vers[2], build: vers[3] }),
            RobotMessage::SetupOutputs { recipe_id: rid, types: types.clone() },
            RobotMessage::SetupInputs { recipe_id: id, types: types.clone() },
            RobotMessage::StartAccepted(flag),
            RobotMessage::PauseAccepted(flag),
            RobotMessage::DataPackage { recipe_id: rid, values: payload.clone() },
            RobotMessage::Text(text.clone()),
        ] {
            let bytes = m.encode(version).unwrap();
            let (raw, used) = split_package(&bytes).unwrap().unwrap();
            prop_assert_eq!(used, bytes.len());
            prop_assert_eq!(RobotMessage::decode(version, raw).unwrap(), m);
        }
    }

    #[test]
    fn garbage_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..300), version in any_version()) {
        if let Ok(Some((raw, _))) = split_package(&bytes) {
            let _ = HostMessage::decode(version, raw);
            let _ = RobotMessage::decode(version, raw);
        }
    }
}
