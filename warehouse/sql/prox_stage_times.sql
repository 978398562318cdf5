-- Mean time per case of each proximity stage.
SELECT avg(t_render_ns) / 1e6 AS render_ms, avg(t_blob_paper_ns) / 1e6 AS blob_paper_ms,
       avg(t_blob_subpixel_ns) / 1e6 AS blob_subpixel_ms, avg(t_total_ns) / 1e6 AS total_ms
FROM prox_cases WHERE run = $run;
