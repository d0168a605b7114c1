"""Training of the torchvision Faster R-CNN apple detector and its export to ONNX (needs the `export` extra)."""
