// A run of matrix-vector products and few-query attentions (a decoding step's embedding, layers and head)
// as one persistent kernel: every block of the grid takes its share of a task, then waits at a grid-wide
// barrier for the others before the next task, which reads what the last one wrote. A step of `paper` is
// 123 dependent kernels otherwise, each paying its start and its drain; here it pays a barrier instead
// (opt-in, `UMGEN_CHAIN=1`: measured slower than the kernels one by one).
//
// Compiled after `gemv.cu` and `attend.cu` with `UMGEN_CHAIN` defined (their bodies without their kernels).
// The grid must be resident at once (a cooperative launch: at most the SMs × the blocks each holds).

struct ChainTask {
    int kind;  // CHAIN_GEMV or CHAIN_ATTEND
    int pad_;
    union {
        Gemv g;
        AttendRows a;
    };
};
#define CHAIN_GEMV 0
#define CHAIN_ATTEND 1

struct Chain {
    const ChainTask* tasks;
    unsigned* bar;  // [0] blocks arrived at the current barrier, [1] barriers passed (zero at first)
    int count;
    int task_bytes;  // sizeof(ChainTask) as the launcher lays the tasks out
};

// Task `t` as block `bx` of `nb`: a product walks its column groups by `nb`, an attention takes its blocks
// (batch, row, head, split) in turn, the shared memory free again between two of them.
DEV void chain_task(const ChainTask& t, long long bx, long long nb) {
    if (t.kind == CHAIN_GEMV) {
        gemv_run(t.g, bx, nb, false);
        return;
    }
    const long long total = (long long)t.a.heads * t.a.rows * t.a.splits * t.a.batches;
    for (long long blk = bx; blk < total; blk += nb) {
        attend_rows_block(t.a, blk, false);
        sync_block();
    }
}

#ifdef UMGEN_EMULATED
// The host emulator runs one block at a time, so no block could wait for another: each task runs as its own
// grid of `grid` blocks (a grid's end is the barrier).
static void chain_emulated(const Chain& P, long long grid) {
    for (int i = 0; i < P.count; i++) {
        const ChainTask t = P.tasks[i];
        run_grid([t] { chain_task(t, block_x(), blocks()); }, grid, 8);
    }
}
#else
// Every block arrives; the last one resets the count and moves the generation on, which the others wait
// for. The fences make each block's writes before the barrier visible to every block after it (as
// cooperative groups' grid sync does).
DEV void grid_barrier(unsigned* bar, unsigned nb) {
    sync_block();
    if (thread_id() == 0) {
        unsigned gen;
        asm volatile("ld.relaxed.gpu.global.u32 %0, [%1];" : "=r"(gen) : "l"(bar + 1) : "memory");
        fence();
        if (atomicAdd(bar, 1u) + 1 == nb) {
            atomicExch(bar, 0u);
            fence();
            atomicAdd(bar + 1, 1u);
        } else {
            unsigned now = gen;
            while (now == gen) asm volatile("ld.acquire.gpu.global.u32 %0, [%1];" : "=r"(now) : "l"(bar + 1) : "memory");
        }
        fence();
    }
    sync_block();
}

// Asks L2 for this block's share of task `t`'s weights (a product's; an attention reads only the caches,
// which the task before it wrote), so that they arrive while the current task runs.
DEV void chain_prefetch(const ChainTask& t, long long bx, long long nb) {
    if (t.kind != CHAIN_GEMV) return;
    const char* w = (const char*)t.g.w;
    const long long lines = ((long long)t.g.n * t.g.k * (long long)sizeof(WT) + 127) / 128;
    for (long long l = bx * threads() + thread_id(); l < lines; l += nb * threads()) prefetch_l2(w + l * 128);
}

KERNEL umgen_chain(const Chain P) {
    SHARED ChainTask cur;
    if (P.task_bytes != (int)sizeof(ChainTask)) __trap();
    const long long bx = block_x(), nb = blocks();
    for (int i = 0; i < P.count; i++) {
        // The task's parameters into shared memory, a word a thread: every thread reads them many times.
        const int* src = (const int*)(P.tasks + i);
        for (int e = thread_id(); e < (int)(sizeof(ChainTask) / 4); e += threads()) ((int*)&cur)[e] = src[e];
        sync_block();
        if (i + 1 < P.count) chain_prefetch(P.tasks[i + 1], bx, nb);
        chain_task(cur, bx, nb);
        grid_barrier(P.bar, (unsigned)nb);
    }
}
#endif
