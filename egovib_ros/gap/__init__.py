"""Sim-to-real gap diagnosis (numpy/scipy only; see docs/gap.md).

Entry points: `pipeline.run_gap` (model and bag files in, report directory out),
`pipeline.diagnose_recording` (a Recording against a NoiseModel), `diagnose.diagnose` of a
`features.build_table` table with `diagnose.DiagnosisOptions`, `change.diagnose_change`,
`writeback.write_back`, `advice.advise`, `report.build_report`. The blind validations are
experiments: research/egovib_research/experiments/gap_validation.py, gap_real_injection.py.
"""
