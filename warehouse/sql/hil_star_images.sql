-- Star hardware-in-the-loop run: one row per image (boresight, roll, counts, errors in arcseconds).
SELECT
    image,
    coalesce(error, status)                                 AS status,
    stars_detected,
    stars_identified,
    T,
    degrees(ra_rad)                                          AS ra_deg,
    degrees(dec_rad)                                         AS dec_deg,
    roll_deg,
    truth_source,
    boresight_error_rad * arcsec_per_rad()                 AS boresight_error_arcsec,
    attitude_error_rad * arcsec_per_rad()                  AS attitude_error_arcsec,
    residual_median_rad * arcsec_per_rad()                 AS residual_median_arcsec,
    truth_residual_median_rad * arcsec_per_rad()           AS truth_residual_median_arcsec,
    truth_ids_agree,
    truth_ids_disagree,
    degrees(altaz_error_rad)                                 AS altaz_error_deg,
    alt_method,
    alt_T,
    alt_boresight_error_rad * arcsec_per_rad()             AS alt_boresight_error_arcsec,
    t_total_ns / 1e6                                         AS ms
FROM hil_star
WHERE run = $run
ORDER BY case_id;
