"""Equations of motion: the ballistic descent, powered flight with a step API."""
