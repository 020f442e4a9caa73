"""The robot and its kinematics: DH tables, forward kinematics, the base-to-world frame,
classical identification, per-joint error maps, acceptable poses, tool centre points, URDF."""
