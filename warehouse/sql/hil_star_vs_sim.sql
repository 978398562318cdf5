-- Real against simulated runs of the same camera: a star HIL run ($run, datasets hil_star and
-- hil_star_stars) beside a star SIL run ($sim_run, star_cases and star_detections), both voting methods
-- of the simulation.  Errors in arcseconds against each run's truth; "identified" = T > 0.
-- Boresight error = angle between the third rows (camera +z) of A_est and A_true (star_cases: boresight_err_rad).
SELECT source, method, cases, identified_rate, success_rate, median_stars_observed, median_stars_identified,
       mean_T, median_boresight_error_arcsec, median_attitude_error_arcsec, median_residual_arcsec FROM (
    SELECT 1 AS k, 'real' AS source, any_value(method) AS method, count(*) AS cases,
           avg((T > 0)::DOUBLE) AS identified_rate,
           avg((status = 'success')::DOUBLE) AS success_rate,
           median(stars_detected) AS median_stars_observed,
           median(stars_identified) FILTER (WHERE T > 0) AS median_stars_identified,
           avg(T) FILTER (WHERE T > 0) AS mean_T,
           median(boresight_error_rad) * arcsec_per_rad() AS median_boresight_error_arcsec,
           median(attitude_error_rad) * arcsec_per_rad() AS median_attitude_error_arcsec,
           (SELECT median(residual_rad) FROM hil_star_stars WHERE run = $run) * arcsec_per_rad()
               AS median_residual_arcsec
    FROM hil_star WHERE run = $run AND error IS NULL
    UNION ALL
    SELECT 2, 'sim', 'paper', count(*),
           avg((T > 0)::DOUBLE),
           avg((status = 'success')::DOUBLE),
           median(n_observed),
           median(n_identified) FILTER (WHERE T > 0),
           avg(T) FILTER (WHERE T > 0),
           median(boresight_err_rad::DOUBLE) FILTER (WHERE isfinite(boresight_err_rad)) * arcsec_per_rad(),
           median(err_total_rad::DOUBLE) FILTER (WHERE isfinite(err_total_rad)) * arcsec_per_rad(),
           (SELECT median(residual_rad) FROM star_detections
             WHERE run = $sim_run AND accepted AND isfinite(residual_rad)) * arcsec_per_rad()
    FROM star_cases WHERE run = $sim_run
    UNION ALL
    SELECT 3, 'sim', 'robust', count(*),
           avg((T_robust > 0)::DOUBLE),
           avg((status_robust = 'success')::DOUBLE),
           median(n_observed),
           median(n_identified_robust) FILTER (WHERE T_robust > 0),
           avg(T_robust) FILTER (WHERE T_robust > 0),
           NULL,
           median(err_total_robust_rad) FILTER (WHERE isfinite(err_total_robust_rad)) * arcsec_per_rad(),
           NULL
    FROM star_cases WHERE run = $sim_run AND status_robust IS NOT NULL
)
ORDER BY k;
