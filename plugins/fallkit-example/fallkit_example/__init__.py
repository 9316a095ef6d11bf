"""fallkit-example: one reward term (`root_spin`) and one sampler (`standing_push`), see docs/plugins.md."""
