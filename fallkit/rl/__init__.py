"""Learning: actor and critic models, PPO, the Trainer, checkpoints, policy loading, ONNX export."""
