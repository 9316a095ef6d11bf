"""The falling environment: FallEnv (TorchRL EnvBase), observations, reward terms, samplers.

`fallkit.env.build.make_env(config, spec)` builds a run's env from its config.
"""
