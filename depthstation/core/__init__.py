"""The core every stage stands on: camera model, geometry, boards, protocols, capture format, grid,
results contract, device protocol, errors. It imports nothing from the stages above it."""
