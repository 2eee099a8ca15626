"""Sim-to-real gap diagnosis (numpy/scipy only; see docs/gap.md).

Public entry points:
    run_gap(model_path, real_path, out_dir, *, write_back=False, options=None, ...)
                                                          -> report dict   (pipeline)
    diagnose_recording(rec, model, *, options=None)       -> Diagnosis     (pipeline)
    diagnose(table, options=None), build_table(rec, model)  (diagnose, features)
    DiagnosisOptions(folds=5, train_fraction=None, alpha=0.01, effects=..., seed=0,
                     reference_lag_s=0.0, lag_tolerance_s=0.005, window_blocks=...)
    simulator_reference_lag(model)                                       (simref)
    write_back(diagnosis, sim_params_path, out_yaml)                     (writeback)
    advise(diagnosis) -> what to do, the denoiser's cost, what is left   (advice)

The blind validations (simulator, alternate reality, real flight with injected effects)
are experiments: research/egovib_research/experiments/gap_validation.py, gap_real_injection.py.
"""
