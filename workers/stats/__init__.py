"""Statistics: render counters and phase times, image quality, block statistics."""
