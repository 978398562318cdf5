-- The reference's Table 3 per true range, for both range estimators of one sweep run, beside the
-- reference's own numbers (Sec. 2.3).  "within" = true range inside the estimator's [min, max].
WITH ref(true_range_m, ref_avg_est_m, ref_avg_abs_err_m, ref_avg_rel_err_pct, ref_within_pct) AS (
    VALUES (1.000, 1.392, 0.3921, 39.21, 0.0), (1.585, 1.738, 0.1840, 11.61, 77.78),
           (2.512, 2.537, 0.1961, 7.808, 88.89), (3.981, 3.837, 0.3991, 10.03, 77.78),
           (6.310, 5.951, 0.4992, 7.912, 88.89), (10.00, 8.685, 1.345, 13.45, 44.44),
           (15.85, 13.11, 2.734, 17.25, 22.22), (25.12, 19.99, 5.131, 20.43, 33.33),
           (39.81, 30.15, 9.657, 24.26, 11.11), (63.10, 42.40, 20.69, 32.79, 0.0),
           (100.0, 50.50, 49.50, 49.50, 0.0)
), runs AS (
    SELECT * FROM prox_cases WHERE run = $run AND job = 'sweep'
), per_range AS (
    SELECT
        range_index,
        any_value(true_range_m)                                                         AS true_range_m,
        count(*)                                                                        AS cases,
        avg(found::DOUBLE) * 100                                                        AS found_pct,
        avg(paper_range_est_m)                                                          AS paper_avg_est_m,
        avg(abs(paper_range_est_m - true_range_m))                                      AS paper_avg_abs_err_m,
        avg(abs(paper_range_est_m - true_range_m) / true_range_m) * 100                 AS paper_avg_rel_err_pct,
        avg((true_range_m BETWEEN paper_range_min_m AND paper_range_max_m)::DOUBLE) * 100 AS paper_within_pct,
        avg(subpixel_range_est_m)                                                       AS subpixel_avg_est_m,
        avg(abs(subpixel_range_est_m - true_range_m))                                   AS subpixel_avg_abs_err_m,
        avg(abs(subpixel_range_est_m - true_range_m) / true_range_m) * 100              AS subpixel_avg_rel_err_pct,
        avg((true_range_m BETWEEN subpixel_range_min_m AND subpixel_range_max_m)::DOUBLE) * 100
                                                                                        AS subpixel_within_pct
    FROM runs
    GROUP BY range_index
)
SELECT p.*, r.ref_avg_est_m, r.ref_avg_abs_err_m, r.ref_avg_rel_err_pct, r.ref_within_pct
FROM per_range p
LEFT JOIN ref r ON abs(r.true_range_m - p.true_range_m) < 0.005 * p.true_range_m
ORDER BY p.true_range_m;
