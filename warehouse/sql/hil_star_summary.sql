-- Star hardware-in-the-loop run: one summary row (every image, identified or not, counted once).
-- Errors against the run's truth (a truth file or the tripod's alt/az), in arcseconds.
SELECT
    count(*)                                                           AS images,
    count(*) FILTER (WHERE error IS NOT NULL)                          AS errors,
    count(*) FILTER (WHERE identified)                                 AS identified,
    count(*) FILTER (WHERE status = 'success')                         AS success,
    count(*) FILTER (WHERE status = 'confident_wrong')                 AS confident_wrong,
    any_value(method)                                                  AS method,
    median(stars_detected)                                             AS median_stars_detected,
    median(stars_identified) FILTER (WHERE identified)                 AS median_stars_identified,
    avg(T) FILTER (WHERE identified)                                   AS mean_T,
    median(boresight_error_rad) * arcsec_per_rad()                   AS median_boresight_error_arcsec,
    max(boresight_error_rad) * arcsec_per_rad()                      AS max_boresight_error_arcsec,
    median(attitude_error_rad) * arcsec_per_rad()                    AS median_attitude_error_arcsec,
    median(residual_median_rad) * arcsec_per_rad()                   AS median_residual_arcsec,
    (SELECT median(residual_rad) FROM hil_star_stars WHERE run = $run) * arcsec_per_rad()
                                                                       AS all_stars_median_residual_arcsec,
    sum(truth_ids_agree)                                               AS truth_ids_agree,
    sum(truth_ids_disagree)                                            AS truth_ids_disagree,
    any_value(alt_method)                                              AS alt_method,
    count(*) FILTER (WHERE alt_identified)                             AS alt_identified,
    median(alt_boresight_error_rad) * arcsec_per_rad()               AS alt_median_boresight_error_arcsec,
    avg(t_total_ns) / 1e6                                              AS mean_ms_per_image
FROM hil_star
WHERE run = $run;
