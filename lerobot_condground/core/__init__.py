"""Names and data every stage shares (conditions, label codes, the UR3e's kinematic spec, the paper's numbers); imports neither MuJoCo nor torch."""
