-- The reference's Table 6 for every image of a star hardware-in-the-loop run: each identified star's
-- catalog id (HIP), magnitude and observed-versus-predicted error (arcsec; predicted with the solved
-- attitude), and the same against the truth attitude when there is one.  Brightest first per image.
SELECT
    case_id,
    image,
    hip,
    vmag,
    residual_rad * arcsec_per_rad()        AS error_arcsec,
    truth_residual_rad * arcsec_per_rad()  AS truth_error_arcsec,
    x_px,
    y_px,
    pred_x_px,
    pred_y_px,
    truth_id_agrees
FROM hil_star_stars
WHERE run = $run
ORDER BY case_id, vmag, hip;
