"""fallkit: learn soft, stylized falls for legged robots (Robot Crash Course)."""

__version__ = "0.1.0"
