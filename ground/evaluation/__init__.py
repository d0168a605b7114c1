"""Evaluation against a simulated flight's truth: the association on perturbed truth (evaluate), whole-flight registration (register_flight), counting baselines and synthetic inputs."""
