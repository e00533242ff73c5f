"""Trainers (RepresentationTrainer, WorldModelTrainer)."""
