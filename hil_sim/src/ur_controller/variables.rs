//! The RTDE variable names the simulated controller serves (RTDE guide, "Field names and
//! associated types"): every output the `ur-rtde` receive interface asks for by default,
//! the general purpose registers, and the inputs a client may own.

use super::core::{ControllerSnapshot, Registers, REGISTER_COUNT};
use firmware_iface::rtde::{DataType, Value};

fn register_index(name: &str, prefix: &str, range: std::ops::Range<usize>) -> Option<usize> {
    let i: usize = name.strip_prefix(prefix)?.parse().ok()?;
    range.contains(&i).then_some(i)
}

/// The value of output `name` in `s`, or None when the controller does not know the name.
pub fn output_value(name: &str, s: &ControllerSnapshot) -> Option<Value> {
    use Value::*;
    let r = &s.registers;
    let zero6 = Vector6d([0.0; 6]);
    Some(match name {
        "timestamp" => Double(s.time),
        "target_q" => Vector6d(s.target_q),
        "target_qd" => Vector6d(s.target_qd),
        "target_qdd" => Vector6d(s.target_qdd),
        "target_current"
        | "target_moment"
        | "actual_current"
        | "joint_control_output"
        | "actual_TCP_force"
        | "ft_raw_wrench"
        | "payload_inertia"
        | "actual_current_as_torque"
        | "actual_current_window" => zero6,
        "actual_q" => Vector6d(s.actual_q),
        "actual_qd" => Vector6d(s.actual_qd),
        "actual_TCP_pose" => Vector6d(s.actual_tcp_pose),
        "actual_TCP_speed" | "target_TCP_speed" => Vector6d(s.actual_tcp_speed),
        "target_TCP_pose" => Vector6d(s.target_tcp_pose),
        "joint_temperatures" => Vector6d([35.0; 6]),
        "actual_joint_voltage" => Vector6d([48.0; 6]),
        "actual_digital_input_bits" | "actual_digital_output_bits" => Uint64(0),
        "actual_execution_time" => Double(0.4),
        "robot_mode" => Int32(s.robot_mode.code()),
        "joint_mode" => Vector6Int32(
            [match s.robot_mode.code() {
                7 => 253,
                5 => 255,
                _ => 236,
            }; 6],
        ),
        "safety_mode" | "safety_status" => Int32(s.safety_mode.code()),
        "actual_tool_accelerometer" => Vector3d([0.0, 0.0, 9.81]),
        "speed_scaling" | "target_speed_fraction" => Double(r.speed_slider),
        "actual_momentum"
        | "actual_robot_current"
        | "io_current"
        | "tcp_force_scalar"
        | "standard_analog_input0"
        | "standard_analog_input1"
        | "standard_analog_output0"
        | "standard_analog_output1"
        | "tool_analog_input0"
        | "tool_analog_input1"
        | "tool_output_current"
        | "euromap67_24V_current"
        | "payload" => Double(0.0),
        "actual_main_voltage" | "actual_robot_voltage" | "euromap67_24V_voltage" => Double(48.0),
        "tool_temperature" => Double(30.0),
        "runtime_state" => Uint32(s.runtime_state()),
        "robot_status_bits" => Uint32(s.robot_status_bits()),
        "safety_status_bits" => Uint32(s.safety_status_bits()),
        "elbow_position" | "elbow_velocity" | "payload_cog" => Vector3d([0.0; 3]),
        "analog_io_types"
        | "tool_mode"
        | "tool_analog_input_types"
        | "euromap67_input_bits"
        | "euromap67_output_bits"
        | "script_control_line" => Uint32(0),
        "tool_output_voltage" => Int32(24),
        "tool_output_mode" | "tool_digital_output0_mode" | "tool_digital_output1_mode" => Uint8(0),
        "output_bit_registers0_to_31" => Uint32(r.output_bits as u32),
        "output_bit_registers32_to_63" => Uint32((r.output_bits >> 32) as u32),
        "input_bit_registers0_to_31" => Uint32(r.input_bits as u32),
        "input_bit_registers32_to_63" => Uint32((r.input_bits >> 32) as u32),
        _ => {
            if let Some(i) = register_index(name, "output_int_register_", 0..REGISTER_COUNT) {
                Int32(r.output_int[i])
            } else if let Some(i) =
                register_index(name, "output_double_register_", 0..REGISTER_COUNT)
            {
                Double(r.output_double[i])
            } else if let Some(i) = register_index(name, "output_bit_register_", 64..128) {
                Bool(r.output_bits >> i & 1 == 1)
            } else if let Some(i) = register_index(name, "input_int_register_", 0..REGISTER_COUNT) {
                Int32(r.input_int[i])
            } else if let Some(i) =
                register_index(name, "input_double_register_", 0..REGISTER_COUNT)
            {
                Double(r.input_double[i])
            } else if let Some(i) = register_index(name, "input_bit_register_", 64..128) {
                Bool(r.input_bits >> i & 1 == 1)
            } else {
                return None;
            }
        }
    })
}

/// The type of input `name`, or None when the controller has no such input.
pub fn input_type(name: &str) -> Option<DataType> {
    Some(match name {
        "standard_digital_output_mask"
        | "standard_digital_output"
        | "configurable_digital_output_mask"
        | "configurable_digital_output"
        | "tool_digital_output_mask"
        | "tool_digital_output"
        | "standard_analog_output_mask"
        | "standard_analog_output_type" => DataType::Uint8,
        "standard_analog_output_0" | "standard_analog_output_1" | "speed_slider_fraction" => {
            DataType::Double
        }
        "speed_slider_mask" | "input_bit_registers0_to_31" | "input_bit_registers32_to_63" => {
            DataType::Uint32
        }
        _ => {
            if register_index(name, "input_int_register_", 0..REGISTER_COUNT).is_some() {
                DataType::Int32
            } else if register_index(name, "input_double_register_", 0..REGISTER_COUNT).is_some() {
                DataType::Double
            } else if register_index(name, "input_bit_register_", 64..128).is_some() {
                DataType::Bool
            } else {
                return None;
            }
        }
    })
}

/// Applies input `name` = `value` to the registers (inputs that drive I/O the simulator
/// does not model are accepted and ignored).
pub fn apply_input(name: &str, value: Value, r: &mut Registers) {
    match (name, value) {
        ("speed_slider_fraction", Value::Double(v)) => r.speed_slider = v.clamp(0.0, 1.0),
        ("input_bit_registers0_to_31", Value::Uint32(v)) => {
            r.input_bits = (r.input_bits & !0xffff_ffff) | u128::from(v)
        }
        ("input_bit_registers32_to_63", Value::Uint32(v)) => {
            r.input_bits = (r.input_bits & !(0xffff_ffffu128 << 32)) | (u128::from(v) << 32)
        }
        (_, Value::Int32(v)) => {
            if let Some(i) = register_index(name, "input_int_register_", 0..REGISTER_COUNT) {
                r.input_int[i] = v;
            }
        }
        (_, Value::Double(v)) => {
            if let Some(i) = register_index(name, "input_double_register_", 0..REGISTER_COUNT) {
                r.input_double[i] = v;
            }
        }
        (_, Value::Bool(b)) => {
            if let Some(i) = register_index(name, "input_bit_register_", 64..128) {
                r.input_bits = (r.input_bits & !(1u128 << i)) | (u128::from(b) << i);
            }
        }
        _ => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ur_controller::core::{ArmModel, Core};
    use firmware_iface::dashboard::RobotMode;

    #[test]
    fn outputs_have_the_guide_types_and_unknown_names_are_none() {
        let c = Core::new(
            ArmModel {
                period: 0.008,
                max_accel: 10.0,
                flange_from_tcp: Default::default(),
                floor_z: None,
            },
            [0.1; 6],
            RobotMode::Running,
        );
        let s = c.snapshot();
        let t = |n| output_value(n, &s).map(|v| v.data_type());
        assert_eq!(t("timestamp"), Some(DataType::Double));
        assert_eq!(t("actual_q"), Some(DataType::Vector6d));
        assert_eq!(t("robot_mode"), Some(DataType::Int32));
        assert_eq!(t("runtime_state"), Some(DataType::Uint32));
        assert_eq!(t("joint_mode"), Some(DataType::Vector6Int32));
        assert_eq!(t("output_int_register_24"), Some(DataType::Int32));
        assert_eq!(t("output_bit_register_64"), Some(DataType::Bool));
        assert_eq!(t("output_int_register_48"), None);
        assert_eq!(t("no_such_thing"), None);
        assert_eq!(
            output_value("actual_q", &s),
            Some(Value::Vector6d([0.1; 6]))
        );
        assert_eq!(output_value("robot_mode", &s), Some(Value::Int32(7)));
    }

    #[test]
    fn inputs_reach_the_registers() {
        let mut r = Registers::default();
        assert_eq!(input_type("input_int_register_24"), Some(DataType::Int32));
        assert_eq!(
            input_type("input_double_register_29"),
            Some(DataType::Double)
        );
        assert_eq!(input_type("input_int_register_99"), None);
        apply_input("input_int_register_24", Value::Int32(-1), &mut r);
        apply_input("input_double_register_29", Value::Double(0.5), &mut r);
        apply_input("input_bit_register_70", Value::Bool(true), &mut r);
        assert_eq!(r.input_int[24], -1);
        assert_eq!(r.input_double[29], 0.5);
        assert_eq!(r.input_bits >> 70 & 1, 1);
    }
}
