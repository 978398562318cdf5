-- Nightly metrics of one proximity run ($run: sweep or trajectory), one row per case
-- (jobs/nightly/compare.py: METRICS["prox_sweep"], METRICS["prox_trajectory"]).  NULL = not applicable.
--   found                        a blob was found
--   within_{paper,subpixel}      the true range lies in the estimator's [range_min, range_max] (false when found
--                                but the bounds are not finite)
--   range_rel_err_*              |estimate - true| / true;  range_bias_*: (estimate - true) / true
--   dir_err_arcsec               angle between the centre of brightness' direction and the true direction
--   pos_err_{x,y,z}_m            |estimated - true| position per camera axis (subpixel estimator)
SELECT case_id,
       found,
       CASE WHEN found THEN coalesce(true_range_m BETWEEN paper_range_min_m AND paper_range_max_m, false) END
                                                                               AS within_paper,
       CASE WHEN found THEN coalesce(true_range_m BETWEEN subpixel_range_min_m AND subpixel_range_max_m, false) END
                                                                               AS within_subpixel,
       CASE WHEN found THEN abs(paper_range_est_m - true_range_m) / true_range_m END    AS range_rel_err_paper,
       CASE WHEN found THEN abs(subpixel_range_est_m - true_range_m) / true_range_m END AS range_rel_err_subpixel,
       CASE WHEN found THEN (paper_range_est_m - true_range_m) / true_range_m END       AS range_bias_paper,
       CASE WHEN found THEN (subpixel_range_est_m - true_range_m) / true_range_m END    AS range_bias_subpixel,
       CASE WHEN found THEN dir_err_rad * arcsec_per_rad() END                        AS dir_err_arcsec,
       CASE WHEN found THEN abs(subpixel_x_m - true_x_m) END                            AS pos_err_x_m,
       CASE WHEN found THEN abs(subpixel_y_m - true_y_m) END                            AS pos_err_y_m,
       CASE WHEN found THEN abs(subpixel_z_m - true_z_m) END                            AS pos_err_z_m
FROM prox_cases
WHERE run = $run
ORDER BY case_id;
