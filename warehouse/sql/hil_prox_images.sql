-- Proximity hardware-in-the-loop: every image x threshold of one run (unreadable images: one row, error set).
-- error_pct is signed, (estimate - truth) / truth in %.
SELECT
    image,
    threshold,
    error,
    found,
    n_pixels,
    round(axis_ratio, 4)                                                AS axis_ratio,
    truth_range_m,
    range_min_m,
    range_m,
    range_max_m,
    100 * range_error_m / truth_range_m                                 AS error_pct,
    within_min_max,
    touches_edge
FROM hil_prox
WHERE run = $run
ORDER BY case_id, threshold;
