-- Reliability summary of one star-tracker run (reference section 3.3).
-- success: all three axis errors (Eqs. 4-7) <= 100 arcsec; confident_wrong: failed with T > 0;
-- no_solution: failed with T <= 0.  *_robust: dualsight's voting options on the same detections.  Means of Table 5 are over the successful cases, as in the reference.
-- Full scan of star_cases.  `star report` reads star_summ_summary.sql (the per-shard summaries, same numbers) when
-- every shard of the run has one, and this file for runs made before the summaries (jobs/reports/star.py).
SELECT
    count(*)                                                        AS cases,
    avg((status = 'success')::DOUBLE)                               AS success_rate,
    avg((status = 'confident_wrong')::DOUBLE)                       AS confident_wrong_rate,
    avg((status = 'no_solution')::DOUBLE)                           AS no_solution_rate,
    avg(id_correct::DOUBLE)                                         AS identification_rate,
    avg((status_robust = 'success')::DOUBLE)                       AS robust_success_rate,
    avg((status_robust = 'confident_wrong')::DOUBLE)               AS robust_confident_wrong_rate,
    avg((status_robust = 'no_solution')::DOUBLE)                   AS robust_no_solution_rate,
    avg(id_correct_robust::DOUBLE)                                 AS robust_identification_rate,
    avg(n_generated) FILTER (WHERE status = 'success')              AS mean_stars_generated,
    avg(n_observed) FILTER (WHERE status = 'success')               AS mean_stars_observed,
    avg(T) FILTER (WHERE status = 'success')                        AS mean_T,
    avg(abs(err_x_rad)) FILTER (WHERE status = 'success') * arcsec_per_rad() AS mean_err_x_arcsec,
    avg(abs(err_y_rad)) FILTER (WHERE status = 'success') * arcsec_per_rad() AS mean_err_y_arcsec,
    avg(abs(err_z_rad)) FILTER (WHERE status = 'success') * arcsec_per_rad() AS mean_err_z_arcsec,
    avg(n_generated)                                                AS mean_stars_generated_all,
    avg((n_generated >= 3)::DOUBLE)                                 AS sky_share_ge3_stars,
    avg((n_generated >= 4)::DOUBLE)                                 AS sky_share_ge4_stars,
    avg(t_total_ns) / 1e6                                           AS mean_ms_per_case
FROM star_cases
WHERE run = $run;
