-- Proximity hardware-in-the-loop: the threshold sweep of one run (the reference's Figure 8 numbers).
-- One row per threshold, over the run's images that could be read.  Ranges in metres.
--   avg_range_m          mean estimate (Eq. 1 with the area table's estimate curve) over images with a blob
--   avg_range_min/max_m  mean of the min / max ranges (the error bars)
--   avg_abs_error_m      mean |estimate - truth| (the reference's "average residual"), images with a blob
--   avg_rel_error_pct    mean |estimate - truth| / truth, in %
--   within_min_max_pct   share of the images WITH a truth whose truth lies in [min, max] (no blob = outside;
--                        null when [min, max] is a point for every image: a sphere's area has no orientation spread)
SELECT
    threshold,
    count(*)                                                            AS images,
    count(*) FILTER (WHERE found)                                       AS found,
    count(truth_range_m)                                                AS with_truth,
    avg(range_m) FILTER (WHERE found)                                   AS avg_range_m,
    avg(range_min_m) FILTER (WHERE found)                               AS avg_range_min_m,
    avg(range_max_m) FILTER (WHERE found)                               AS avg_range_max_m,
    avg(truth_range_m)                                                  AS avg_truth_m,
    avg(abs_error_m)                                                    AS avg_abs_error_m,
    100 * avg(rel_error)                                                AS avg_rel_error_pct,
    100 * median(rel_error)                                             AS median_rel_error_pct,
    100.0 * count(*) FILTER (WHERE within_min_max)
          / nullif(count(within_min_max), 0)                            AS within_min_max_pct,
    avg(n_pixels) FILTER (WHERE found)                                  AS avg_n_pixels,
    avg(axis_ratio) FILTER (WHERE found)                                AS avg_axis_ratio,
    count(*) FILTER (WHERE touches_edge)                                AS touching_edge
FROM hil_prox
WHERE run = $run AND error IS NULL
GROUP BY threshold
ORDER BY threshold;
