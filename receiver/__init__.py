"""The receive half: event sources, the virtual event camera and the decoding pipeline."""
