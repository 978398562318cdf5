-- Star tracking: per mode, frames, error per axis (RMS over the frames with an attitude, arcsec) and the latency
-- per frame of the tracker (t_nav_ns: tracking, fallback, rates and the attitude filter) and of its stages (ms); lost-in-space run
-- beside tracking on the same frames (shadow_lost_in_space) in the last column.  One run ($run).
SELECT
    mode,
    count(*)                                             AS frames,
    sqrt(avg(err_x_arcsec * err_x_arcsec))               AS rms_err_x_arcsec,
    sqrt(avg(err_y_arcsec * err_y_arcsec))               AS rms_err_y_arcsec,
    sqrt(avg(err_z_arcsec * err_z_arcsec))               AS rms_err_z_arcsec,
    avg(n_used)                                          AS mean_stars_used,
    avg(t_nav_ns) / 1e6                                  AS ms_per_frame,
    quantile_cont(t_nav_ns, 0.99) / 1e6                  AS p99_ms_per_frame,
    avg(t_predict_ns) / 1e6                              AS predict_ms,
    avg(t_track_ns) / 1e6                                AS track_ms,
    avg(t_lis_ns) / 1e6                                  AS lost_in_space_ms,
    avg(t_filter_ns) / 1e6                               AS filter_ms,
    avg(coalesce(t_render_ns, 0) + coalesce(t_detect_ns, 0)) / 1e6 AS render_detect_ms,
    avg(t_shadow_lis_ns) / 1e6                           AS shadow_lost_in_space_ms
FROM star_frames
WHERE run = $run
GROUP BY mode
ORDER BY CASE mode WHEN 'tracking' THEN 0 WHEN 'lost_in_space' THEN 1 ELSE 2 END;
