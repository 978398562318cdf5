-- The reference's method beside dualsight's robust voting options, on the same detections.
-- Full scan of star_cases.  `star report` reads star_summ_robust.sql (the per-shard summaries, same numbers) when
-- every shard of the run has one, and this file for runs made before the summaries (jobs/reports/star.py).
SELECT method, success_rate, confident_wrong_rate, no_solution_rate, identification_rate,
       mean_err_x_arcsec, mean_err_y_arcsec, mean_err_z_arcsec FROM (
    SELECT 1 AS k, 'reference (paper)' AS method,
           avg((status = 'success')::DOUBLE) AS success_rate,
           avg((status = 'confident_wrong')::DOUBLE) AS confident_wrong_rate,
           avg((status = 'no_solution')::DOUBLE) AS no_solution_rate,
           avg(id_correct::DOUBLE) AS identification_rate,
           avg(abs(err_x_rad)) FILTER (WHERE status = 'success') * arcsec_per_rad() AS mean_err_x_arcsec,
           avg(abs(err_y_rad)) FILTER (WHERE status = 'success') * arcsec_per_rad() AS mean_err_y_arcsec,
           avg(abs(err_z_rad)) FILTER (WHERE status = 'success') * arcsec_per_rad() AS mean_err_z_arcsec
    FROM star_cases WHERE run = $run
    UNION ALL
    SELECT 2, 'robust (dualsight)',
           avg((status_robust = 'success')::DOUBLE),
           avg((status_robust = 'confident_wrong')::DOUBLE),
           avg((status_robust = 'no_solution')::DOUBLE),
           avg(id_correct_robust::DOUBLE),
           avg(abs(err_x_robust_rad)) FILTER (WHERE status_robust = 'success') * arcsec_per_rad(),
           avg(abs(err_y_robust_rad)) FILTER (WHERE status_robust = 'success') * arcsec_per_rad(),
           avg(abs(err_z_robust_rad)) FILTER (WHERE status_robust = 'success') * arcsec_per_rad()
    FROM star_cases WHERE run = $run AND status_robust IS NOT NULL
)
ORDER BY k;
