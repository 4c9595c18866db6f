//! Hardware-in-the-loop simulator: UR controller, Robotiq gripper and D455 cameras on loopback.
//!
//! Modules: [`ur_controller`] (RTDE, dashboard and secondary servers with the servo
//! dynamics), [`gripper`] (Robotiq 2F-85 emulator behind Modbus RTU, URCap and CAN),
//! [`scene`] (table, objects, the arm as capsules) and [`depth_camera`] (D455-like
//! depth/IR/colour by ray casting with parry3d, with the sensor's noise model).
//!
//! Every server and device keeps the time of an injected [`cell_types::Clock`]: the wall
//! clock ([`cell_types::SystemClock`]) for the real cell's pace, [`cell_types::ScaledClock`]
//! to run faster than real time, or [`cell_types::TickClock`], whose time the simulated
//! controller moves one control cycle at a time, waiting while a servo program plays for its
//! driver's answer to each cycle (lockstep): the simulated cell of `equact run`, `eval` and
//! `demos collect`, at any `--sim-speed` and bit for bit repeatable.

pub mod depth_camera;
pub mod gripper;
pub mod scene;
pub mod ur_controller;
