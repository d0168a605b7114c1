"""Onboard node (drone companion computer): video frames + MAVLink telemetry -> ONNX detector -> zenoh.

Must import and run without torch.
"""
