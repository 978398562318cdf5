-- Trajectory run (reference Fig. 6): per-axis position error of both estimators over the frames where
-- the target was found.
SELECT
    count(*)                                                      AS frames,
    sum(found::INT)                                               AS frames_found,
    min(true_range_m)                                             AS min_range_m,
    max(true_range_m)                                             AS max_range_m,
    avg(abs(paper_x_m - true_x_m))                                AS paper_mean_abs_err_x_m,
    avg(abs(paper_y_m - true_y_m))                                AS paper_mean_abs_err_y_m,
    avg(abs(paper_z_m - true_z_m))                                AS paper_mean_abs_err_z_m,
    avg(abs(paper_range_est_m - true_range_m) / true_range_m) * 100 AS paper_mean_rel_range_err_pct,
    avg(abs(subpixel_x_m - true_x_m))                             AS subpixel_mean_abs_err_x_m,
    avg(abs(subpixel_y_m - true_y_m))                             AS subpixel_mean_abs_err_y_m,
    avg(abs(subpixel_z_m - true_z_m))                             AS subpixel_mean_abs_err_z_m,
    avg(abs(subpixel_range_est_m - true_range_m) / true_range_m) * 100 AS subpixel_mean_rel_range_err_pct,
    avg(dir_err_rad) * arcsec_per_rad()                         AS mean_direction_err_arcsec
FROM prox_cases
WHERE run = $run AND job = 'trajectory' AND found;
