"""The paper's experiments: ``reproduce`` (Tables I-III, Fig. 4, rounds curve) and the
bandwidth comparison (Table III, rate-distortion against image codecs)."""
