"""Stage 2's parts, one concept per file: the branches and their condition maps (branches), the relit
branch's encoding (encoding), the physics-first output (physics_first), the paper's physics terms
(physics_terms) and the conditioning intrinsics (conditions). The Task that trains them is
pilight.train.relight; evaluation imports from here, never from pilight.train."""
