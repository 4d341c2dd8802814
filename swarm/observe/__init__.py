"""Observation: telemetry collection, recordings, the live dashboard, reports and plots."""
