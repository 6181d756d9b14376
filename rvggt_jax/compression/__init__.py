"""RegimeVGGT compression of the global blocks (token merging + K/V downsampling)."""
