-- Star tracking: error per axis against time (RMS over the sequences of one run, $run, at each frame), with the
-- share of the sequences whose attitude is valid and within the limit at that frame.
SELECT
    frame,
    avg(t_s)                                 AS t_s,
    avg(within_limit::INT)                   AS availability,
    sqrt(avg(err_x_arcsec * err_x_arcsec))   AS rms_err_x_arcsec,
    sqrt(avg(err_y_arcsec * err_y_arcsec))   AS rms_err_y_arcsec,
    sqrt(avg(err_z_arcsec * err_z_arcsec))   AS rms_err_z_arcsec
FROM star_frames
WHERE run = $run
GROUP BY frame
ORDER BY frame;
