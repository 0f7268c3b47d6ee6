"""The contract between offline and runtime: head spec, link map, skin predictor, file formats."""
