//! The printed report of `calibconv bench`: the table of layer rows, the goals, the memory.

use super::*;

pub(super) fn fmt_load(l: Option<[f64; 3]>) -> String {
    l.map_or("-".into(), |l| {
        format!("{:.2} {:.2} {:.2}", l[0], l[1], l[2])
    })
}

pub(super) fn merge_memory(
    results: &mut [ShapeResult],
    unet: &mut [UnetResult],
    mem: &MemoryReport,
) {
    for (r, m) in results.iter_mut().zip(&mem.layers) {
        r.conv2d_peak_mib = m[0];
        r.calibrated.peak_mib = m[1];
        r.calibrated.peak_ratio = ratio(m[1], m[0]);
        if let Some(a) = r.aten.as_mut() {
            a.peak_mib = m[2];
            a.peak_ratio = ratio(m[2], m[0]);
        }
    }
    for (u, m) in unet.iter_mut().zip(&mem.unet) {
        u.conv2d_peak_mib = m[0];
        u.calibrated_peak_mib = m[1];
        u.peak_ratio = ratio(m[1], m[0]);
    }
}

pub(super) fn print_memory(results: &[ShapeResult], unet: &[UnetResult]) {
    if !results.is_empty() {
        println!("\npeak memory of one training step (separate process, mmap threshold pinned):");
        println!(
            "{:>7} {:>2} {:>4} {:>4} {:>8} | {:>8} {:>8} {:>5}",
            "net", "B", "Cin", "Cout", "HxW", "conv MiB", "cal MiB", "x"
        );
    }
    for r in results {
        println!(
            "{:>7} {:>2} {:>4} {:>4} {:>8} | {:>8} {:>8} {:>5}",
            r.net,
            r.batch,
            r.c_in,
            r.c_out,
            format!("{}x{}", r.height, r.width),
            fmt_opt(r.conv2d_peak_mib, 1),
            fmt_opt(r.calibrated.peak_mib, 1),
            fmt_opt(r.calibrated.peak_ratio, 2),
        );
    }
    for u in unet {
        println!(
            "U-Net ({}) step peak: conv2d {} MiB, calibrated {} MiB ({}x)",
            u.network,
            fmt_opt(u.conv2d_peak_mib, 0),
            fmt_opt(u.calibrated_peak_mib, 0),
            fmt_opt(u.peak_ratio, 2)
        );
    }
}

pub(super) fn fmt_opt(v: Option<f64>, prec: usize) -> String {
    v.map_or("-".to_string(), |v| format!("{v:.prec$}"))
}

pub(super) fn print_header(aten: bool) {
    println!(
        "\n{:>7} {:>2} {:>2} {:>4} {:>4} {:>8} | {:>8} {:>8} {:>5} {:>11} {:>5} | {:>8} {:>8} {:>5} {:>11} {:>5} | {:>4} {:>4} {:>4}{}",
        "net",
        "n",
        "B",
        "Cin",
        "Cout",
        "HxW",
        "conv fwd",
        "cal fwd",
        "x",
        "95% ci",
        "cpu x",
        "conv f+b",
        "cal f+b",
        "x",
        "95% ci",
        "cpu x",
        "goal",
        "fwd",
        "f+b",
        if aten { " | aten fwd x  f+b x" } else { "" }
    );
}

/// An interval as the table prints it.
pub(super) fn fmt_ci(ci: Option<[f64; 2]>) -> String {
    ci.map_or("-".to_string(), |[lo, hi]| format!("[{lo:.2},{hi:.2}]"))
}

pub(super) fn print_row(r: &ShapeResult) {
    let c = &r.calibrated;
    let goal = r.goal.as_ref().map_or("-".to_string(), |g| {
        format!(
            "{:>4.2} {:>4} {:>4}",
            g.limit,
            g.forward.mark(),
            g.forward_backward.mark()
        )
    });
    let mut line = format!(
        "{:>7} {:>2} {:>2} {:>4} {:>4} {:>8} | {:>8.2} {:>8.2} {:>5.2} {:>11} {:>5} | {:>8.2} {:>8.2} {:>5.2} {:>11} {:>5} | {goal}",
        r.net,
        r.count,
        r.batch,
        r.c_in,
        r.c_out,
        format!("{}x{}{}", r.height, r.width, if r.input_grad { "" } else { "*" }),
        c.forward.reference_ms,
        c.forward.candidate_ms,
        c.forward.ratio,
        fmt_ci(c.forward.ratio_ci),
        fmt_opt(c.forward.cpu_ratio, 2),
        c.forward_backward.reference_ms,
        c.forward_backward.candidate_ms,
        c.forward_backward.ratio,
        fmt_ci(c.forward_backward.ratio_ci),
        fmt_opt(c.forward_backward.cpu_ratio, 2),
    );
    if let Some(a) = &r.aten {
        line.push_str(&format!(
            " | {:>10.2} {:>6.2}",
            a.forward.ratio, a.forward_backward.ratio
        ));
    }
    println!("{line}");
}

/// The outcomes of the rows' goals, counted per pass, and the rows where one does not hold.
pub(super) fn print_goals(results: &[ShapeResult]) {
    let goals: Vec<(&ShapeResult, &Goal)> = results
        .iter()
        .filter_map(|r| r.goal.as_ref().map(|g| (r, g)))
        .collect();
    if goals.is_empty() {
        return;
    }
    println!(
        "\ngoals (README, Performance: <= 1.3x conv2d for tiny and small, <= 1.15x from 64 \
         channels in and out), from each ratio's 95% interval (ok: within, OVER: above, ?: \
         inconclusive):"
    );
    for (pass, get) in [
        ("forward", (|g: &Goal| g.forward) as fn(&Goal) -> Outcome),
        ("forward+backward", |g: &Goal| g.forward_backward),
    ] {
        let count = |o: Outcome| goals.iter().filter(|(_, g)| get(g) == o).count();
        let missed: Vec<String> = goals
            .iter()
            .filter(|(_, g)| get(g) != Outcome::Holds)
            .map(|(r, g)| {
                format!(
                    "{} {}->{} {}x{} ({})",
                    r.net,
                    r.c_in,
                    r.c_out,
                    r.height,
                    r.width,
                    get(g).mark()
                )
            })
            .collect();
        println!(
            "  {pass}: {} of {} hold, {} contradicted, {} inconclusive{}{}",
            count(Outcome::Holds),
            goals.len(),
            count(Outcome::Contradicted),
            count(Outcome::Inconclusive),
            if missed.is_empty() { "" } else { ": " },
            missed.join(", ")
        );
    }
}
