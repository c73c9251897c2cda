"""Schemes: the one-step integration schemes and attitude forms, their closed-form Jacobian
blocks written once against a block layout, the block algebra, the rotating world's
transition, and one preintegration step of each scheme. Imports :mod:`jaximu.geometry`.
"""
