//! D455 camera models, board detection, hand-eye and joint bundle adjustment, cloud fusion.
