"""Metrics, scoring of prediction folders, result files, tables, charts and the job grid."""
