"""Sim-to-real gap diagnosis (numpy/scipy only; see docs/gap.md).

Public entry points:
    run_gap(model_path, real_path, out_dir, *, write_back=False, ...)  -> report dict   (pipeline)
    diagnose_recording(rec, model, *, reference_lag_s=0.0, ...)         -> Diagnosis     (pipeline)
    diagnose(table, ...), build_table(rec, model)                        (diagnose, features)
    simulator_reference_lag(model)                                       (simref)
    write_back(diagnosis, sim_params_path, out_yaml)                     (writeback)
    advise(diagnosis) -> what to do, the denoiser's cost, what is left   (advice)

The blind validations (simulator, alternate reality, real flight with injected effects)
are experiments: egovib_ros/experiments/gap_validation.py, gap_real_injection.py.
"""
