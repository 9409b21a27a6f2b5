"""Scripted experts: one state machine per task over the privileged anchors, and the episode runner.

Import the submodules directly (``keygen.expert.runner``, ``keygen.expert.pour``, ...).
"""
