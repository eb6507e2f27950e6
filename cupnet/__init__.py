"""cupnet: hip cup 3D pose from one X-ray under cone-beam geometry."""

__version__ = "0.1.0"
