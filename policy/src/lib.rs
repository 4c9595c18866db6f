//! The EquAct SE(3)-equivariant keyframe policy: network, weights, inference, training, scripted experts.
