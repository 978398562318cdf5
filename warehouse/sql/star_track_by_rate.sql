-- Star tracking: the normal frames (no blank/blinded/dropped event) by true body rate, in bins of 0.2 deg/s: how many,
-- the share with a valid attitude within the limit (availability), withheld as degraded (stated sigma above
-- tracking.max_sigma_rad), without any answer, and the mean stated largest 1-sigma (arcsec) and post-fit RMS (in
-- centroid sigmas) of the answers.  One run ($run).  Smear grows with the rate, and with it the centroid errors.
SELECT
    floor(sqrt(true_rate_x_deg_s * true_rate_x_deg_s + true_rate_y_deg_s * true_rate_y_deg_s
               + true_rate_z_deg_s * true_rate_z_deg_s) / 0.2) * 0.2          AS rate_from_deg_s,
    count(*)                                                                  AS frames,
    avg(within_limit::INT)                                                    AS availability,
    avg(coalesce(degraded, false)::INT)                                       AS degraded_share,
    avg((NOT valid AND NOT coalesce(degraded, false))::INT)                   AS no_answer_share,
    avg(sigma_max_arcsec)                                                     AS mean_sigma_max_arcsec,
    avg(residual_rms_sigma)                                                   AS mean_rms_sigma
FROM star_frames
WHERE run = $run AND event = 'normal'
GROUP BY 1
ORDER BY 1;
