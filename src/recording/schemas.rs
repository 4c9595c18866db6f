//! JSON Schemas written into each recording's schema records.
//!
//! The `foxglove.*` schemas describe the fields of Foxglove's well-known message types as
//! we write them (Foxglove selects its panels by the schema name); the test suite checks our
//! messages against Foxglove's own published schemas independently. `equact.*` schemas are
//! ours.

const TIME: &str = r#"{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0,"maximum":999999999}},"required":["sec","nsec"]}"#;
const VEC3: &str = r#"{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}},"required":["x","y","z"]}"#;
const QUAT: &str = r#"{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}},"required":["x","y","z","w"]}"#;
const COLOR: &str = r#"{"type":"object","properties":{"r":{"type":"number"},"g":{"type":"number"},"b":{"type":"number"},"a":{"type":"number"}},"required":["r","g","b","a"]}"#;

fn pose() -> String {
    format!(
        r#"{{"type":"object","properties":{{"position":{VEC3},"orientation":{QUAT}}},"required":["position","orientation"]}}"#
    )
}

/// The schema text for a schema name of [`super::TOPICS`].
pub fn schema_for(name: &str) -> String {
    match name {
        "foxglove.JointStates" => format!(
            r#"{{"title":"foxglove.JointStates","type":"object","properties":{{"timestamp":{TIME},"joints":{{"type":"array","items":{{"type":"object","properties":{{"name":{{"type":"string"}},"position":{{"type":"number"}},"velocity":{{"type":"number"}},"acceleration":{{"type":"number"}},"effort":{{"type":"number"}}}},"required":["name"]}}}}}},"required":["timestamp","joints"]}}"#
        ),
        "foxglove.FrameTransforms" => format!(
            r#"{{"title":"foxglove.FrameTransforms","type":"object","properties":{{"transforms":{{"type":"array","items":{{"type":"object","properties":{{"timestamp":{TIME},"parent_frame_id":{{"type":"string"}},"child_frame_id":{{"type":"string"}},"translation":{VEC3},"rotation":{QUAT}}},"required":["timestamp","parent_frame_id","child_frame_id","translation","rotation"]}}}}}},"required":["transforms"]}}"#
        ),
        "foxglove.RawImage" => format!(
            r#"{{"title":"foxglove.RawImage","type":"object","properties":{{"timestamp":{TIME},"frame_id":{{"type":"string"}},"width":{{"type":"integer"}},"height":{{"type":"integer"}},"encoding":{{"type":"string"}},"step":{{"type":"integer"}},"data":{{"type":"string","contentEncoding":"base64"}}}},"required":["timestamp","frame_id","width","height","encoding","step","data"]}}"#
        ),
        "foxglove.PointCloud" => format!(
            r#"{{"title":"foxglove.PointCloud","type":"object","properties":{{"timestamp":{TIME},"frame_id":{{"type":"string"}},"pose":{pose},"point_stride":{{"type":"integer"}},"fields":{{"type":"array","items":{{"type":"object","properties":{{"name":{{"type":"string"}},"offset":{{"type":"integer"}},"type":{{"type":"integer"}}}},"required":["name","offset","type"]}}}},"data":{{"type":"string","contentEncoding":"base64"}}}},"required":["timestamp","frame_id","pose","point_stride","fields","data"]}}"#,
            pose = pose()
        ),
        "foxglove.SceneUpdate" => format!(
            r#"{{"title":"foxglove.SceneUpdate","type":"object","properties":{{"deletions":{{"type":"array"}},"entities":{{"type":"array","items":{{"type":"object","properties":{{"timestamp":{TIME},"frame_id":{{"type":"string"}},"id":{{"type":"string"}},"lifetime":{TIME},"frame_locked":{{"type":"boolean"}},"metadata":{{"type":"array"}},"arrows":{{"type":"array","items":{{"type":"object","properties":{{"pose":{pose},"shaft_length":{{"type":"number"}},"shaft_diameter":{{"type":"number"}},"head_length":{{"type":"number"}},"head_diameter":{{"type":"number"}},"color":{COLOR}}}}}}},"cubes":{{"type":"array"}},"spheres":{{"type":"array"}},"cylinders":{{"type":"array"}},"lines":{{"type":"array","items":{{"type":"object","properties":{{"type":{{"type":"integer"}},"pose":{pose},"thickness":{{"type":"number"}},"scale_invariant":{{"type":"boolean"}},"points":{{"type":"array","items":{VEC3}}},"color":{COLOR},"colors":{{"type":"array"}},"indices":{{"type":"array"}}}}}}}},"triangles":{{"type":"array"}},"texts":{{"type":"array"}},"models":{{"type":"array"}}}},"required":["timestamp","frame_id","id","lifetime","frame_locked","metadata","arrows","cubes","spheres","cylinders","lines","triangles","texts","models"]}}}}}},"required":["deletions","entities"]}}"#,
            pose = pose()
        ),
        "foxglove.Log" => format!(
            r#"{{"title":"foxglove.Log","type":"object","properties":{{"timestamp":{TIME},"level":{{"type":"integer","minimum":0,"maximum":5}},"message":{{"type":"string"}},"name":{{"type":"string"}},"file":{{"type":"string"}},"line":{{"type":"integer"}}}},"required":["timestamp","level","message","name","file","line"]}}"#
        ),
        "equact.RobotDescription" => r#"{"title":"equact.RobotDescription","type":"object","properties":{"data":{"type":"string","description":"URDF of the robot"}},"required":["data"]}"#.to_string(),
        "equact.GripperState" => r#"{"title":"equact.GripperState","type":"object","properties":{"activated":{"type":"boolean"},"width_m":{"type":"number"},"object":{"type":"string"},"current_a":{"type":"number"},"fault":{"type":["string","null"]}},"required":["activated","width_m","object","current_a"]}"#.to_string(),
        "equact.JointTrajectory" => r#"{"title":"equact.JointTrajectory","type":"object","properties":{"step":{"type":"integer"},"period_s":{"type":"number","exclusiveMinimum":0},"positions":{"type":"array","items":{"type":"array","items":{"type":"number"},"minItems":6,"maxItems":6}},"velocities":{"type":"array","items":{"type":"array","items":{"type":"number"},"minItems":6,"maxItems":6}},"accelerations":{"type":"array","items":{"type":"array","items":{"type":"number"},"minItems":6,"maxItems":6}},"max_velocity":{"type":"array","items":{"type":"number"}},"max_acceleration":{"type":"array","items":{"type":"number"}},"max_jerk":{"type":"array","items":{"type":"number"}},"tracking_bound":{"type":"number"}},"required":["step","period_s","positions","velocities","accelerations","max_velocity","max_acceleration","max_jerk","tracking_bound"]}"#.to_string(),
        "equact.StepEvent" => r#"{"title":"equact.StepEvent","type":"object","properties":{"step":{"type":"integer"},"phase":{"type":"string"},"duration_s":{"type":"number"},"detail":{"type":"string"}},"required":["step","phase","duration_s","detail"]}"#.to_string(),
        "equact.EpisodeOutcome" => r#"{"title":"equact.EpisodeOutcome","type":"object","properties":{"outcome":{"type":"string"},"success":{"type":"boolean"},"steps":{"type":"integer"},"detail":{"type":"string"}},"required":["outcome","success","steps","detail"]}"#.to_string(),
        other => format!(r#"{{"title":"{other}","type":"object"}}"#),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_topic_schema_is_valid_json_with_its_title() {
        for (_, name) in crate::recording::TOPICS {
            let text = schema_for(name);
            let v: serde_json::Value = serde_json::from_str(&text)
                .unwrap_or_else(|e| panic!("schema {name} is not JSON: {e}"));
            assert_eq!(v["title"], *name);
            assert_eq!(v["type"], "object");
        }
    }
}
